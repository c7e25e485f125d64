"""``rig`` command line: one entry point, one subcommand per job.

Every subcommand takes ``--config FILE`` (TOML); without it the built-in defaults of
``controller.config`` apply.  Errors in the configuration or the inputs are reported in
one line naming what is wrong and what is allowed, with exit status 2 and no traceback:
the configuration is loaded first (its errors name the key), then every argument is
checked as it is parsed (:mod:`rig.argtypes`), then an output file that exists is
refused unless the command has ``--force``; file errors while the command runs are one
line too.  Text of the user's (keys, values, file names, recorded strings) is echoed
through :func:`rig.terminal.safe`: control characters escaped, at most 1000 characters.
``--json`` output is strict JSON (:mod:`rig.strict_json`: NaN and infinities
are ``null``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from controller.config import ConfigError, load_config
from rig.argtypes import OneLineParser, bind_config, overwrite_problem
from rig.blas_threads import one_blas_thread
from rig.rt.kernel_cache import drop_stale_kernel_cache
from rig.rt.stop_signals import StopRequested, StopSignals
from rig.terminal import refuse

#: subcommands that SIGTERM / SIGINT stop cleanly at any point (rig.rt.stop_signals): the
#: handlers are installed before anything of theirs runs
STOPPABLE = ("run", "demo")

#: subcommand -> (module under rig.commands, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "design": ("design", "design the LQG bank and write the versioned artifact (.npz)"),
    "analyze": ("analyze", "linear closed-loop covariance analysis against passive"),
    "sim": ("sim", "fast offline closed-loop simulation against the emulated rig"),
    "montecarlo": ("montecarlo", "Monte Carlo robustness runs over parameter spread"),
    "hil": ("hil", "run the emulated rig as a CAN node"),
    "run": ("run", "run the real-time controller service on a CAN bus"),
    "demo": ("demo", "service against the emulated rig (own process) in real time"),
    "study": ("study", "control performance study: tables and figures"),
    "tune": ("tune", "search the LQ weights over Monte Carlo plants and roads (optuna)"),
    "replay": ("replay", "replay a recorded run (MCAP or candump log) through the loop"),
    "report": ("report", "HTML report with plots of a recorded run"),
    "export": ("export", "export a recorded run to ASAM MDF 4 (signals + CAN bus log) or "
                         "Parquet"),
    "identify": ("identify", "identify the rig (masses, rates, tire, actuator) from an "
                             "excitation run"),
    "check-host": ("check_host", "can this computer run the loop? wake-up latency against "
                                 "the timing budgets"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (keeps start-up light)."""
    parser = OneLineParser(prog="rig", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--config", metavar="FILE", default=None,
                       help="rig configuration (TOML); default: built-in defaults")
        if name == command:
            mod = importlib.import_module(f"rig.commands.{module}")
            mod.add_arguments(p)
            p.set_defaults(_module=mod)
    return parser


def _config_path(command: str, argv: list[str]) -> str | None:
    """The ``--config`` value of ``argv`` (parsed before the rest: some arguments are
    checked against the configuration)."""
    pre = OneLineParser(prog=f"rig {command}", add_help=False)
    pre.add_argument("--config", default=None)
    known, _ = pre.parse_known_args(argv)
    return known.config


#: exceptions a command lets through and the one line each becomes: qualified class name ->
#: (text before the message, text after it, exit status).  Keyed by name so that the
#: commands' heavy modules are imported only by the command that runs; the most derived
#: class of an exception that has an entry wins.
REFUSALS: dict[str, tuple[str, str, int]] = {
    "rig.rt.stop_signals.StopRequested": (
        "", " before the control loop started; nothing recorded", 0),
    "controller.config.ConfigError": ("", "", 2),
    "controller.artifact.DesignMismatch": ("design artifact: ", "", 2),
    "hil.sim.roads.RoadError": ("", "", 2),
    "hil.rig_process.RigProcessError": ("emulated rig: ", "", 2),
    "rig.recording.recorder.RecorderStartError": ("", "", 2),
    "rig.recording.scan.RecordingError": ("", "", 2),
    "hil.batch.ClusterError": ("", "", 2),
    "hil.tune.TuneError": ("", "", 2),
    "rig.extras.MissingExtraError": ("", "", 2),
}


def refusal(exc: BaseException) -> tuple[str, int] | None:
    """The one line (without the ``rig COMMAND:`` prefix) and exit status for ``exc``, or
    None when it is not a refusal (a bug: the traceback is wanted)."""
    for cls in type(exc).__mro__:
        entry = REFUSALS.get(f"{cls.__module__}.{cls.__qualname__}")
        if entry is not None:
            before, after, code = entry
            return f"{before}{exc}{after}", code
    if isinstance(exc, OSError):
        return _os_error(exc), 2
    return None


def _os_error(exc: OSError) -> str:
    if exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    one_blas_thread()
    drop_stale_kernel_cache()
    command = next((a for a in argv if not a.startswith("-")), None)
    stop = StopSignals().install() if command in STOPPABLE else None
    try:
        return _main(command, argv, stop)
    finally:
        bind_config(None)
        if stop is not None:
            stop.restore()


def _main(command: str | None, argv: list[str], stop: StopSignals | None) -> int:
    known = command in SUBCOMMANDS
    parser = build_parser(command if known else None)
    try:
        if known:
            assert command is not None
            path = _config_path(command, argv)
            try:
                bind_config(load_config(path) if path is not None else None)
            except ConfigError as exc:
                refuse(command, exc)
                return 2
        args, extra = parser.parse_known_args(argv)
    except SystemExit as exc:        # --help, or a bad argument (one line said why)
        return exc.code if isinstance(exc.code, int) else 2
    if extra:
        refuse(args.command, f"unrecognized arguments: {' '.join(extra)} "
                             f"(see `rig {args.command} --help`)")
        return 2
    problem = overwrite_problem(args)
    if problem:
        refuse(args.command, problem)
        return 2
    args.stop_signals = stop
    try:
        return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (Exception, StopRequested) as exc:
        said = refusal(exc)
        if said is None:
            raise
        refuse(args.command, said[0])
        return said[1]


if __name__ == "__main__":
    sys.exit(main())
