"""``rig`` command line: one entry point, one subcommand per job.

Every subcommand takes ``--config FILE`` (TOML); without it the built-in defaults of
``controller.config`` apply.  Errors in the configuration or the inputs are reported in
one line naming what is wrong, with exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from controller.config import ConfigError
from rig.stop_signals import StopSignals

#: subcommands that SIGTERM / SIGINT stop cleanly at any point (rig.stop_signals): the
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
    "replay": ("replay", "replay a recorded run (MCAP or candump log) through the loop"),
    "report": ("report", "HTML report with plots of a recorded run"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (keeps start-up light)."""
    parser = argparse.ArgumentParser(prog="rig", description=__doc__.splitlines()[0])
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


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    stop = StopSignals().install() if command in STOPPABLE else None
    try:
        parser = build_parser(command if command in SUBCOMMANDS else None)
        args = parser.parse_args(argv)
        args.stop_signals = stop
        return int(args._module.run(args) or 0)
    except ConfigError as exc:
        print(f"rig {args.command}: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        print(f"rig {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    finally:
        if stop is not None:
            stop.restore()


if __name__ == "__main__":
    sys.exit(main())
