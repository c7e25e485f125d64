"""The telemetry process (rig/telemetry_process, docs/telemetry.md): the Zenoh session
and the live Foxglove view in a process of their own, fed by the loop.  SIGKILLed during
a run, control goes on, the loss is recorded and in the status, and the process is
restarted (or, past its restart limit, the status says why not)."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

from controller.config import default_config
from rig.recording.run_data import read_run
from tests.support.processes import sigterm_and_wait
from tests.support.stepped_service import SteppedService
from tests.support.zenoh_client import client_session, free_port, query, wait_for


def _lost_notes(details: list[Any]) -> list[dict[str, Any]]:
    return [d for d in details if isinstance(d, dict) and d.get("telemetry_process") == "lost"]


def test_sigkill_of_the_telemetry_process_during_a_run(tmp_path: Path) -> None:
    port = free_port()
    cfg = default_config().replace(
        telemetry={"endpoints": [f"tcp/127.0.0.1:{port}"], "commands_enabled": True},
        foxglove={"enabled": True, "port": 0})
    rec = tmp_path / "run.mcap"
    rig = SteppedService(cfg, record=str(rec))
    svc, loop = rig.svc, rig.svc.loop
    link = svc.telemetry
    try:
        assert link.wait_connected(20), link.status()
        first = link.pid
        assert first is not None and first != os.getpid()
        assert svc.foxglove.state == "serving"
        s2 = client_session(port)
        try:
            assert wait_for(lambda: bool(query(s2, "rig/status")), 30)
        finally:
            s2.close()
        ticks = loop.tick_count
        os.kill(first, signal.SIGKILL)          # our own grandchild: the service's
        assert wait_for(lambda: link.status()["process"]["losses"] == 1, 30)
        assert wait_for(lambda: link.status()["process"]["state"] == "running"
                        and link.pid not in (None, first), 30), link.status()
        assert link.wait_connected(30)
        assert wait_for(lambda: svc.foxglove.state == "serving", 30)
        s2 = client_session(port)
        try:   # the new process answers status queries and takes commands
            assert wait_for(lambda: bool(query(s2, "rig/status")), 30)
            got = query(s2, "rig/cmd/disarm")
            assert got and got[0][1]["command"] == "disarm", got
        finally:
            s2.close()
        assert loop.tick_count > ticks            # control went on
        status = svc.status()
        assert status["fault"] == "NONE" and status["lifecycle"] == "INACTIVE"
        proc = status["telemetry"]["process"]
        assert proc["restarts"] == 1 and proc["losses"] == 1
        assert "killed by signal 9" in proc["last_loss"]
    finally:
        rig.close()
    run = read_run(rec)
    notes = _lost_notes([e.detail for e in run.events if e.kind == "note"])
    assert len(notes) == 1, notes
    assert notes[0]["exit_status"] == -signal.SIGKILL and notes[0]["restart_in_s"] == 0.5
    assert all(e.detail.get("to") != "FAULT" for e in run.events
               if e.kind in ("lifecycle", "fault") and isinstance(e.detail, dict))


def test_past_its_restart_limit_the_process_stays_down_and_says_why() -> None:
    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design
    from rig.service.loop import tick_record_layout
    from rig.telemetry_process.link import TelemetryLink

    port = free_port()
    cfg = default_config().replace(telemetry={"endpoints": [f"tcp/127.0.0.1:{port}"]})
    layout = tick_record_layout(BankRuntime(cached_design(cfg), cfg=cfg))
    notes: list[Any] = []

    class Loop:
        def request(self, name: str, argument: Any = None, timeout_s: float | None = 1.0
                    ) -> Any:
            raise AssertionError("no command was sent")

        def record_note(self, detail: Any) -> None:
            notes.append(detail)

    link = TelemetryLink(cfg, layout, zenoh=True, foxglove=False, status_provider=dict,
                         restart_attempts=0)
    try:
        assert link.wait_connected(20), link.status()
        pid = link.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        assert wait_for(lambda: link.status()["process"]["state"] == "lost", 30)
        link.poll(Loop())
        assert not link.offer_event(0, 0, "note", {}) and link.dropped >= 1
    finally:
        link.close()
    (note,) = _lost_notes(notes)
    assert note["restart_in_s"] is None and "not restarted" in note["reason"]
    assert "not restarted" in str(link.status()["process"]["last_loss"])


def test_demo_under_never_reading_clients_and_a_status_flood(tmp_path: Path) -> None:
    """``rig demo --timing lockstep`` with Zenoh telemetry and the live view, while 50
    Foxglove clients subscribe to everything and never read and a Zenoh client sends
    status queries at about 1,000/s: the run latches no fault and runs every tick, the
    flood is refused by the rate limits (counted in the status the process answers), the
    log holds no line a client wrote.  Counts, never timing (lockstep: the loop's
    results do not depend on the machine's load); the demo is long and ended by SIGTERM
    once the status has been read, so a slow host cannot end it before the flood does
    (8 s of lockstep once ran out under load)."""
    import contextlib
    import json
    import subprocess
    import sys
    import threading
    import time

    import zenoh
    from websockets.sync.client import ClientConnection, connect

    from tests.support.foxglove_demo import SUBPROTOCOLS, connect_when_up

    zport, fport = free_port(), free_port()
    conf = tmp_path / "rig.toml"
    conf.write_text(f'[telemetry]\nendpoints = ["tcp/127.0.0.1:{zport}"]\n'
                    f'[foxglove]\nenabled = true\nport = {fport}\n')
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "demo", "-q", "--json", "--no-record",
         "--no-realtime", "--timing", "lockstep", "--duration", "600", "--config",
         str(conf)],
        cwd=root, env={**os.environ, "PYTHONPATH": str(root)}, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    clients: list[ClientConnection] = []
    stack = contextlib.ExitStack()
    # a refused status query is not answered: it only ends ("done" counts the ends)
    replies = {"ok": 0, "err": 0, "done": 0}
    lock = threading.Lock()

    def count(reply: Any) -> None:
        with lock:
            replies["ok" if reply.ok is not None else "err"] += 1

    def done() -> None:
        with lock:
            replies["done"] += 1

    try:
        clients.append(stack.enter_context(connect_when_up(f"ws://127.0.0.1:{fport}", proc)))
        for _ in range(49):
            clients.append(stack.enter_context(connect(
                f"ws://127.0.0.1:{fport}", subprotocols=SUBPROTOCOLS,  # type: ignore[arg-type]
                open_timeout=10)))
        for ws in clients:   # subscribe to every channel id the server may have, then stall
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": i} for i in range(1, 16)]}))
        s2 = client_session(zport)
        try:
            assert wait_for(lambda: bool(query(s2, "rig/status")), 60)
            sent = 0
            t0 = time.monotonic()
            while sent < 2000:
                s2.get("rig/status", zenoh.handlers.Callback(count, done), timeout=3.0)
                sent += 1
                time.sleep(max(0.0, t0 + sent * 1e-3 - time.monotonic()))
            assert wait_for(lambda: replies["done"] >= sent, 30), replies
            refused = sent - replies["ok"]
            status: dict[str, Any] = {}

            def other_peer_status() -> bool:
                """A status built after the flood (another key expression: another
                peer's share; the replies are up to 0.2 s old)."""
                got = query(s2, "rig/*")
                if got and got[0][0]:
                    status.update(got[0][1])
                return status.get("telemetry", {}).get("status_refused", 0) >= refused

            assert wait_for(other_peer_status, 30)
        finally:
            s2.close()
        out, err = sigterm_and_wait(proc, 180)
    finally:
        stack.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    summary = json.loads(out)
    assert summary["faults"] == [], summary["faults"]
    assert summary["stopped_by"] == "SIGTERM" and summary["timing"]["ticks"] > 0
    # the flood was rate limited: the refused queries ended without a reply
    assert refused > replies["ok"] > 0 and replies["err"] == 0, replies
    tel = status["telemetry"]
    assert tel["status_refused"] >= refused and tel["process"]["state"] == "running"
    assert status["fault"] == "NONE"
    assert not any(ln.startswith("ERROR rig.service") for ln in err.splitlines()), err[-3000:]


def test_what_the_process_sends_back_is_checked_again() -> None:
    """The telemetry process faces the network, so the loop process trusts nothing it
    sends: lines that are no JSON or no known event are dropped and counted, a command
    with an unknown name (a forged log line in it) or a bad argument is refused by the
    loop side's own validation before the loop sees it, and more than COMMAND_QUEUE
    waiting commands are dropped.  Only a valid command reaches the loop, one per poll."""
    import json

    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design
    from rig.service.lifecycle import CommandResult
    from rig.service.loop import tick_record_layout
    from rig.telemetry_process.link import COMMAND_QUEUE, TelemetryLink
    from rig.wire.protocol import LifecycleState

    cfg = default_config().replace(foxglove={"enabled": True, "port": 0})
    layout = tick_record_layout(BankRuntime(cached_design(cfg), cfg=cfg))
    applied: list[tuple[str, Any]] = []

    class Loop:
        def request(self, name: str, argument: Any = None, timeout_s: float | None = 1.0
                    ) -> CommandResult:
            assert timeout_s is None          # applied at once, in the loop's thread
            applied.append((name, argument))
            return CommandResult(True, LifecycleState.INACTIVE, "ok")

        def record_note(self, detail: Any) -> None:
            raise AssertionError(detail)

    link = TelemetryLink(cfg, layout, zenoh=False, foxglove=True, status_provider=dict)
    try:
        assert link.foxglove.state == "serving"
        child = link._child
        assert child is not None
        bad = [b"not json", b'{"no": "event"}', b'{"event": "shout"}',
               b'{"event": "command", "id": "x", "name": "arm"}']
        for line in bad:
            link._on_line(child, line)
        assert link.lines_dropped == len(bad)
        commands = [
            {"name": "arm\nERROR rig.service.lifecycle: ACTIVE -> FAULT (forged)", "args": {}},
            {"name": "weight_set", "args": {"weight_set": "2; rm -rf"}},
            {"name": "road", "args": {"speed_mps": 1e999, "roughness_gd": 1e-6}},
            {"name": "blending", "args": "fuzzy"},
            {"name": "disarm", "args": {}},
        ]
        for i, c in enumerate(commands):
            link._on_line(child, json.dumps({"event": "command", "id": i, **c}).encode())
        for _ in range(len(commands)):
            link.poll(Loop())
        assert applied == [("disarm", None)]
        for i in range(COMMAND_QUEUE + 4):
            link._on_line(child, json.dumps(
                {"event": "command", "id": 100 + i, "name": "arm", "args": {}}).encode())
        assert link.commands_dropped == 4
        link.poll(Loop())
        assert applied[-1] == ("arm", None) and len(applied) == 2   # one per poll
    finally:
        link.close()
    assert link.foxglove.state == "stopped"


def test_a_stopped_telemetry_process_costs_the_loop_drops_never_a_wait() -> None:
    """The telemetry process stopped (SIGSTOP: it reads nothing): the feed's pipe fills
    and every further item is dropped and counted at once; the loop side never waits.
    Resumed, the process takes the feed again and ends cleanly at close."""
    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design
    from rig.service.loop import tick_record_layout
    from rig.telemetry_process.link import TelemetryLink
    from tests.support.processes import stop_and_wait_stopped

    cfg = default_config().replace(foxglove={"enabled": True, "port": 0})
    layout = tick_record_layout(BankRuntime(cached_design(cfg), cfg=cfg))
    # four pages: the process may not have read the start's layout item when it is
    # stopped (a busy machine), and a one-page pipe then takes no event at all
    link = TelemetryLink(cfg, layout, zenoh=False, foxglove=True, status_provider=dict,
                         pipe_bytes=1 << 14)
    try:
        pid = link.pid
        assert pid is not None and link.foxglove.state == "serving"
        stop_and_wait_stopped(pid)
        try:
            taken = [link.offer_event(k, k, "note", {"k": k, "pad": "x" * 100})
                     for k in range(5000)]
        finally:
            os.kill(pid, signal.SIGCONT)
        assert taken.count(False) == link.dropped > 0
        assert taken.count(True) == link.sent > 0
        assert link.offer_event(0, 0, "note", {}) or wait_for(
            lambda: link.offer_event(0, 0, "note", {}), 30)     # it reads again
    finally:
        link.close()
    assert link.foxglove.state == "stopped" and link.status()["process"]["losses"] == 0
