"""Argument types shared by every ``rig`` subcommand.

Each converter checks one command-line value while the command line is parsed, so a bad
value is refused before anything is opened, designed or run: one line on stderr naming
the argument, what is wrong and what is allowed, exit status 2
(``rig demo: argument --speed: 1e300 is out of range; allowed [0.1, 100] m/s``).
:class:`OneLineParser` makes argparse's own errors (unknown option, missing value,
invalid choice) one line too.

Numeric bounds that the configuration already owns are read from its schema
(:func:`config_real`, :func:`config_int`); the others are documented here.  The weight
set is checked against the configuration given with ``--config``, which
:func:`rig.cli.main` loads first and binds with :func:`bind_config`.

A single output file is returned as :class:`OutputFile`; :func:`overwrite_problem`
(called by ``main`` once all arguments are parsed) refuses an existing one unless the
command has ``--force``.  Recording targets and output directories follow
:mod:`rig.output_paths`.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from controller.config import RigConfig, host_problem
from controller.files import regular_file_problem
from controller.modes import BANK_MODES
from rig.output_paths import new_file_problem, output_dir_problem, recording_target_problem
from rig.terminal import safe

if TYPE_CHECKING:
    from rig.rt.realtime import RealtimeRequest

__all__ = [
    "DEFAULT_RT_PRIORITY",
    "MAX_OFFLINE_S",
    "MAX_SERVICE_S",
    "OneLineParser",
    "OutputFile",
    "active_config",
    "add_batch_options",
    "add_controller_option",
    "add_foxglove_option",
    "add_realtime_options",
    "add_weights_option",
    "bind_config",
    "cluster",
    "config_int",
    "config_real",
    "cpu",
    "foxglove_address",
    "input_file",
    "integer",
    "output_dir",
    "output_file",
    "overwrite_problem",
    "real",
    "realtime_request",
    "recording_target",
    "road",
    "rt_priority",
    "seed",
    "weight_set",
    "with_foxglove",
]

#: longest run of the commands that keep every tick in memory (sim, montecarlo per run,
#: demo, a candump replay): about 0.2 MB per simulated second
MAX_OFFLINE_S = 3600.0
#: longest ``--duration`` of the services (``rig run``, ``rig hil``): 115 days; without
#: ``--duration`` they run until SIGTERM / SIGINT
MAX_SERVICE_S = 1e7

Converter = Callable[[str], Any]


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors on one line: ``<prog>: <message> (see <prog> --help)``."""

    def error(self, message: str) -> NoReturn:
        one_line = safe(" ".join(message.split()))
        self.exit(2, f"{self.prog}: {one_line} (see `{self.prog} --help`)\n")

    def _get_values(self, action: argparse.Action, arg_strings: list[str]) -> Any:
        # Python 3.11's argparse drops a lone '--' even when it is the value of
        # ``--opt=--``, leaving ``[]`` unconverted: convert and check it like any value
        if action.nargs is None and arg_strings == ["--"]:
            value = self._get_value(action, "--")
            self._check_value(action, value)
            return value
        return super()._get_values(action, arg_strings)


def _fail(message: str) -> NoReturn:
    raise argparse.ArgumentTypeError(message)


def _g(x: float) -> str:
    return f"{x:g}"


def _interval(lo: float, hi: float, lo_open: bool, hi_open: bool, unit: str) -> str:
    return (f"{'(' if lo_open else '['}{_g(lo)}, {_g(hi)}{')' if hi_open else ']'}"
            + (f" {unit}" if unit else ""))


def real(lo: float, hi: float, unit: str = "", *, lo_open: bool = False,
         hi_open: bool = False) -> Converter:
    """A finite number in [lo, hi] (an end excluded with ``*_open``)."""
    allowed = _interval(lo, hi, lo_open, hi_open, unit)

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            _fail(f"{text!r} is not a number; allowed {allowed}")
        if not math.isfinite(value):
            _fail(f"{text} is not a finite number; allowed {allowed}")
        if value < lo or value > hi or (lo_open and value == lo) or (hi_open and value == hi):
            _fail(f"{text} is out of range; allowed {allowed}")
        return value

    convert.__name__ = "number"
    return convert


def integer(lo: int, hi: int, unit: str = "") -> Converter:
    """An integer in [lo, hi]."""
    allowed = f"an integer in [{lo}, {hi}]" + (f" {unit}" if unit else "")

    def convert(text: str) -> int:
        try:
            value = int(text, 10)
        except ValueError:
            _fail(f"{text!r} is not an integer; allowed {allowed}")
        if not lo <= value <= hi:
            _fail(f"{text} is out of range; allowed {allowed}")
        return value

    convert.__name__ = "integer"
    return convert


def _config_meta(key: str) -> dict[str, Any]:
    section, name = key.split(".")
    cls = type(getattr(RigConfig(), section))
    (f,) = (f for f in dataclasses.fields(cls) if f.name == name)
    return dict(f.metadata)


def config_real(key: str, unit: str = "") -> Converter:
    """A number in the range the configuration schema allows for ``key``
    (``"section.name"``)."""
    m = _config_meta(key)
    return real(m["lo"], m["hi"], unit, lo_open=m["lo_open"], hi_open=m["hi_open"])


def config_int(key: str) -> Converter:
    """An integer in the range the configuration schema allows for ``key``."""
    m = _config_meta(key)
    return integer(int(m["lo"]), int(m["hi"]))


#: a seed of the road, the sensor noise and random faults (as ``sensors.seed``)
seed = config_int("sensors.seed")


# ---------------------------------------------------------------------------- configuration

_bound: list[RigConfig | None] = [None]


def bind_config(cfg: RigConfig | None) -> None:
    """The configuration that configuration-dependent arguments are checked against
    (None: the built-in defaults)."""
    _bound[0] = cfg


def active_config() -> RigConfig:
    cfg = _bound[0]
    if cfg is None:
        from controller.config import default_config

        cfg = default_config()
    return cfg


def weight_set(text: str) -> int:
    """A 1-based index into ``design.weight_sets`` of the configuration, or 0: the travel
    schedule between the sets of ``design.schedule_weight_sets`` (docs/design.md §12)."""
    n = len(active_config().design.weight_sets)
    allowed = (f"0..{n} (the weight sets of the configuration, design.weight_sets; "
               f"0 = the travel schedule)")
    try:
        value = int(text, 10)
    except ValueError:
        _fail(f"{text!r} is not an integer; allowed {allowed}")
    if not 0 <= value <= n:
        _fail(f"{text} is not a weight set; allowed {allowed}")
    return value


def add_weights_option(parser: argparse.ArgumentParser, default: int | None) -> None:
    """``--weights N`` as every subcommand spells it (``--weight-set`` is a hidden alias);
    ``default`` None = the configuration's ``design.weight_set``."""
    shown = "design.weight_set" if default is None else str(default)
    parser.add_argument("--weights", type=weight_set, default=default, metavar="N",
                        help=f"weight set, 1-based into design.weight_sets; 0 = the travel "
                             f"schedule between comfort and travel sets; the comfort set "
                             f"runs under the travel governor unless "
                             f"design.govern_comfort_set is false (default: {shown})")
    parser.add_argument("--weight-set", dest="weights", type=weight_set,
                        help=argparse.SUPPRESS)


def add_observe_option(parser: argparse.ArgumentParser) -> None:
    """``--observe S`` of the offline runs (``rig sim``, ``rig montecarlo``): the time each
    run observes before arming (``hil.sim.closed_loop.run_closed_loop``'s ``observe_s``)."""
    parser.add_argument("--observe", type=real(0.0, MAX_OFFLINE_S, "s"), default=0.0,
                        metavar="S",
                        help="observe S seconds before arming, as the service does: the "
                             "controller runs from the first sensor reading with the valve "
                             "safe; the road is S + duration long and the metrics cover the "
                             "armed duration (default 0: armed from the start)")


def _mode_name(text: str) -> str:
    """Mode names are typed in lower case; ``single`` is the old name of ``lqg``."""
    name = text.strip().lower()
    return "lqg" if name == "single" else name


def add_controller_option(parser: argparse.ArgumentParser, modes: Sequence[str],
                          default: str, extra: Sequence[str] = ()) -> None:
    """``--controller MODE`` with the mode names of :mod:`controller.modes` (``extra``: a
    command's own values such as ``all``); where only bank modes are allowed (the
    service) ``--blending`` stays a hidden alias."""
    choices = (*modes, *extra)
    parser.add_argument("--controller", type=_mode_name, default=default, choices=choices,
                        metavar="MODE",
                        help=f"controller mode: {', '.join(choices)} (default {default})")
    if set(modes) <= set(BANK_MODES):
        parser.add_argument("--blending", dest="controller", type=_mode_name,
                            choices=choices, help=argparse.SUPPRESS)


# ---------------------------------------------------------------------------- other values

def cluster(text: str) -> Any:
    """A Dask cluster address (:func:`hil.batch.parse_cluster_address`):
    ``tcp://HOST:PORT`` of a running scheduler or ``local:N``."""
    from hil.batch import ClusterAddressError, parse_cluster_address

    try:
        return parse_cluster_address(text)
    except ClusterAddressError as exc:
        _fail(str(exc))


#: most local worker processes a batch command takes
MAX_JOBS = 1024


def add_batch_options(parser: argparse.ArgumentParser) -> None:
    """Where a batch command (study, montecarlo, tune) runs its closed-loop runs, spelt the
    same everywhere: ``--jobs N`` local processes or ``--cluster ADDR`` (not both:
    argparse refuses the pair in one line)."""
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--jobs", type=integer(1, MAX_JOBS), default=None, metavar="N",
                       help="local worker processes (default: all cores; 1 = in-process)")
    where.add_argument("--workers", dest="jobs", type=integer(1, MAX_JOBS),
                       help=argparse.SUPPRESS)          # earlier spelling of --jobs
    where.add_argument("--cluster", type=cluster, default=None, metavar="ADDR",
                       help="run the batch on Dask: tcp://HOST:PORT of a running "
                            "scheduler, or local:N for N worker processes on 127.0.0.1 "
                            "(default: a local process pool; docs/scale-out.md)")


def road(text: str) -> str:
    """A road name of :func:`hil.sim.roads.make_road`; a ``csv:`` file is read and checked."""
    from hil.sim.roads import RoadError, check_road

    try:
        return check_road(text)
    except RoadError as exc:
        _fail(str(exc))


def _fifo_max() -> int:
    try:
        return os.sched_get_priority_max(os.SCHED_FIFO)
    except (AttributeError, OSError):   # not Linux
        return 99


#: a SCHED_FIFO priority (0 = none)
rt_priority = integer(0, _fifo_max())


def cpu(text: str) -> int:
    """A CPU number of this machine."""
    n = os.cpu_count() or 1
    try:
        value = int(text, 10)
    except ValueError:
        _fail(f"{text!r} is not a CPU number; allowed 0..{n - 1}")
    if not 0 <= value < n:
        _fail(f"{text}: this machine has CPUs 0..{n - 1}")
    return value


#: ``--rt-priority``'s default: the loop thread's SCHED_FIFO priority
DEFAULT_RT_PRIORITY = 50


def add_realtime_options(parser: argparse.ArgumentParser, *, host_check: bool = False
                         ) -> None:
    """``--no-realtime``, ``--rt-priority P`` and ``--cpu N`` (repeatable): the loop's
    real-time set-up as ``rig run`` asks for it (:func:`realtime_request`);
    ``host_check``: the help of ``rig check-host``, which measures with the same set-up."""
    parser.add_argument("--no-realtime", action="store_true",
                        help="measure without the real-time set-up" if host_check else
                        "skip the real-time set-up (SCHED_FIFO, mlockall, gc freeze...)")
    parser.add_argument("--rt-priority", type=rt_priority, default=DEFAULT_RT_PRIORITY,
                        metavar="P",
                        help="SCHED_FIFO priority, as `rig run` (0 = none)" if host_check
                        else "SCHED_FIFO priority of the loop thread (0 = none)")
    parser.add_argument("--cpu", type=cpu, action="append", default=None, metavar="N",
                        help="pin to CPU N (repeatable), as `rig run`" if host_check
                        else "pin the loop to CPU N (repeatable)")


def realtime_request(args: argparse.Namespace) -> RealtimeRequest | None:
    """The set-up the options of :func:`add_realtime_options` ask for (None:
    ``--no-realtime``)."""
    from rig.rt.realtime import RealtimeRequest

    if args.no_realtime:
        return None
    return RealtimeRequest(fifo_priority=args.rt_priority, cpus=tuple(args.cpu or ()))


# ---------------------------------------------------------------------------- files

class OutputFile(str):
    """A single output file (checked against ``--force`` by :func:`overwrite_problem`)."""

    __slots__ = ()


def _checked_path(text: str, what: str, problem: Callable[[str], str | None]) -> str:
    """``text`` if it is a non-empty path without a ``problem``, else an argparse error."""
    if not text:
        _fail(f"an empty {what}")
    why = problem(text)
    if why:
        _fail(f"{text}: {why}")
    return text


def output_file(text: str) -> OutputFile:
    """A file to write: not a directory, in an existing directory."""
    return OutputFile(_checked_path(text, "file name",
                                    lambda t: new_file_problem(t, force=True)))


def overwrite_problem(args: argparse.Namespace) -> str | None:
    """Why the parsed ``args`` would overwrite a file (no ``--force``), or None."""
    force = bool(getattr(args, "force", False))
    for value in vars(args).values():
        if isinstance(value, OutputFile):
            problem = new_file_problem(value, force=force)
            if problem:
                return f"{value}: {problem}"
    return None


def output_dir(text: str) -> str:
    """A directory to write into (created if missing; its files are rewritten)."""
    return _checked_path(text, "directory name", output_dir_problem)


def recording_target(text: str) -> str:
    """A new ``.mcap`` path or a directory for a new recording (never overwritten)."""
    return _checked_path(text, "path", recording_target_problem)


def foxglove_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``[IPv6]:PORT`` or ``PORT`` (then 127.0.0.1) of the live Foxglove
    view -> (host, port)."""
    form = "HOST:PORT or PORT (HOST an IP address, default 127.0.0.1; PORT 0-65535)"
    host, sep, port_s = text.strip().rpartition(":")
    if not sep:
        host = "127.0.0.1"
    elif host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not port_s.isdigit() or not 0 <= int(port_s) <= 65535:
        _fail(f"{text!r}: the port must be an integer 0-65535; allowed {form}")
    if host_problem(host):
        _fail(f"{text!r}: {host!r} is not an IP address; allowed {form}")
    return host, int(port_s)


def add_foxglove_option(parser: argparse.ArgumentParser) -> None:
    """``--foxglove HOST:PORT``: serve the live Foxglove view (docs/foxglove.md)."""
    parser.add_argument(
        "--foxglove", type=foxglove_address, default=None, metavar="HOST:PORT",
        help="serve the live Foxglove WebSocket view on HOST:PORT (PORT alone: "
             "127.0.0.1:PORT; default: the [foxglove] section, off)")


def with_foxglove(cfg: RigConfig, address: tuple[str, int] | None) -> RigConfig:
    """``cfg`` with the view turned on at ``address`` (unchanged when None)."""
    if address is None:
        return cfg
    return cfg.replace(foxglove={"enabled": True, "host": address[0], "port": address[1]})


def input_file(text: str) -> str:
    """An existing, readable file (not a directory)."""
    p = Path(text)
    if not p.exists():
        _fail(f"{text}: no such file")
    if p.is_dir():
        _fail(f"{text}: is a directory, expected a file")
    not_regular = regular_file_problem(p)
    if not_regular:
        _fail(f"{text}: {not_regular}")
    if not os.access(p, os.R_OK):
        _fail(f"{text}: not readable")
    return text
