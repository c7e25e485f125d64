"""``rig run``: the real-time controller service on a CAN bus (systemd-ready).

Exit status 0 after SIGTERM / SIGINT / ``--duration`` (valve left in its safe state,
recording closed); 2 for a bad configuration, design artifact or bus; 3 when the
recording asked for with ``--record`` or ``--excite`` could not be written whole (a
full disk: ``rig run: recording PATH FAILED, it is incomplete: ...``).  SIGTERM / SIGINT
before the loop started (while the bank is designed, the bus or the recording opens)
also exit 0, with a message and no recording (:mod:`rig.rt.stop_signals`).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import can

from controller.config import load_config
from controller.modes import BANK_MODES
from rig import argtypes, strict_json
from rig.output_paths import OUTPUT_FAILED
from rig.terminal import refuse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--design", metavar="NPZ", default=None, type=argtypes.input_file,
                   help="design artifact from `rig design` (default: design at start)")
    p.add_argument("--interface", choices=("socketcan", "virtual"), default=None,
                   help="CAN interface (default: can.interface of the config)")
    p.add_argument("--channel", default=None, help="CAN channel, e.g. can0 / vcan0")
    p.add_argument("--arm", action="store_true",
                   help="arm (ACTIVE) as soon as the sensors are healthy")
    p.add_argument("--excite", action="store_true",
                   help="identification run (docs/identify.md): rest passive for "
                        "excitation.rest_s, arm, play the excitation of [excitation] as the "
                        "force reference (the shaker must hold the road at rest), disarm "
                        "and stop 0.5 s after it; record it and `rig identify` the file")
    p.add_argument("--duration", type=argtypes.real(0.0, argtypes.MAX_SERVICE_S, "s",
                                                    lo_open=True),
                   default=None, metavar="S",
                   help="stop after S seconds (default: run until SIGTERM/SIGINT)")
    p.add_argument("--record", metavar="DIR", default=None, type=argtypes.recording_target,
                   help="record the run (MCAP) into DIR or this new .mcap path "
                        "(a recording is never overwritten)")
    p.add_argument("--no-record", action="store_true", help="do not record")
    p.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    argtypes.add_foxglove_option(p)
    argtypes.add_controller_option(p, tuple(BANK_MODES), "fuzzy")
    argtypes.add_weights_option(p, None)
    argtypes.add_realtime_options(p)
    p.add_argument("--json", action="store_true",
                   help="print the final status as strict JSON (null for a non-finite value)")
    p.add_argument("-v", "--verbose", action="store_true")


def run(args: argparse.Namespace) -> int:
    from rig.recording.recorder import RecorderStartError
    from rig.rt.stop_signals import StopSignals
    from rig.service.runner import Service, ServiceOptions

    stop: StopSignals = getattr(args, "stop_signals", None) or StopSignals()
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    cfg = argtypes.with_foxglove(load_config(args.config), args.foxglove)
    rt = argtypes.realtime_request(args)
    opts = ServiceOptions(
        design_path=args.design, interface=args.interface, channel=args.channel,
        arm=args.arm or args.excite, duration_s=args.duration, excite=args.excite,
        record=args.record,
        recording=False if args.no_record else None,
        telemetry=False if args.no_telemetry else None, controller=args.controller,
        weights=args.weights, realtime=rt, host_check=True)
    try:
        service = Service(cfg, opts, stop=stop)
    except RecorderStartError:
        raise                       # a recording problem, said as such (rig.cli.REFUSALS)
    except OSError as exc:
        if exc.filename is not None and args.design is not None \
                and Path(exc.filename) == Path(args.design):
            refuse("run", f"design artifact: {args.design}: {exc.strerror}")
        else:
            refuse("run", f"cannot open the CAN bus: {exc}")
        return 2
    except can.CanError as exc:
        refuse("run", f"cannot open the CAN bus: {exc}")
        return 2
    if service.recording_path is not None:
        refuse("run", f"recording to {service.recording_path}")
    if service.foxglove is not None and service.foxglove.state == "serving":
        refuse("run", f"Foxglove view on {service.foxglove.url} (WebSocket "
               f"subprotocol {service.foxglove.subprotocol}; docs/foxglove.md)")
    code = service.run()
    if service.ticks_run == 0:
        print(f"rig run: stopped by {service.stop_signal or 'request'} before the control "
              "loop started; nothing recorded", file=sys.stderr)
    elif service.stop_signal:
        rec = service.recorder
        note = "" if rec is None else (f"; recording {service.recording_path}: {rec.error}"
                                       if rec.error else
                                       f"; recording {service.recording_path} complete")
        print(f"rig run: stopped by {service.stop_signal} after {service.ticks_run} ticks"
              + note, file=sys.stderr)
    if args.json:
        status = service.loop.status()
        status["exit_reason"] = service.exit_reason
        status["recording"] = str(service.recording_path) if service.recording_path else None
        status["realtime"] = service.realtime_report.as_dict()
        status["telemetry"] = service.status()["telemetry"]
        status["foxglove"] = service.foxglove_status()
        status["host_check"] = service.status()["host_check"]
        status["recording_error"] = service.recording_failure
        print(strict_json.dumps(status))
    failure = service.recording_failure
    if failure:
        refuse("run", failure)
        if code == 0 and (args.excite or args.record):   # the recording was the point
            return OUTPUT_FAILED
    return code
