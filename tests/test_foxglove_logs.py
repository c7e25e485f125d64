"""What a Foxglove client can make the service log (rig.sdk_logs): real clients on
127.0.0.1 against a live view in a process of its own (tests.support.foxglove_attack),
and the filter on its own with a clock of the test's.  Counts records, never timing."""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from websockets.exceptions import ConnectionClosed

from rig.sdk_logs import (
    BURST,
    GLOBAL_BURST,
    MAX_CHARS,
    SDK_LOGGERS,
    WINDOW_S,
    ClientTextFilter,
)
from tests.support.foxglove_attack import FAKE_LINE, FLOOD, UNKNOWN

ROOT = Path(__file__).resolve().parents[1]
SDK_PREFIXES = ("foxglove.", "foxglove_py.", "tungstenite.", "tokio_tungstenite.")


def attack(**env: str) -> dict[str, Any]:
    base = {k: v for k, v in os.environ.items() if k != "FOXGLOVE_LOG_LEVEL"}
    proc = subprocess.run(
        [sys.executable, "-m", "tests.support.foxglove_attack"], cwd=ROOT,
        env={**base, "PYTHONPATH": str(ROOT), **env}, capture_output=True, text=True,
        timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


@pytest.mark.parametrize("env", [{}, {"FOXGLOVE_LOG_LEVEL": ""}], ids=["unset", "empty"])
def test_sdk_records_stay_out_of_python_logging(env: dict[str, str]) -> None:
    """By default the SDK forwards nothing: a flood of invalid messages, forged op names,
    a 100 KB op and 10,000 unknown subscriptions leave no record at all; the service's
    own logging is untouched and the view serves the next client."""
    out = attack(**env)
    sdk = [r for r in out["records"] if r["name"].startswith(SDK_PREFIXES)]
    assert sdk == []
    assert any(r["name"] == "rig.foxglove_server" and r["level"] == "INFO"
               for r in out["records"])
    assert out["served"] and out["state"] == "stopped"


def test_forwarded_sdk_records_are_escaped_capped_and_summarised() -> None:
    """With the SDK's FOXGLOVE_LOG_LEVEL=DEBUG every SDK record is forwarded: each comes
    through a filtered logger, none has a control character or a forged line of its own,
    none is longer than the cap (plus a summary), and the flood is a few records plus a
    summary instead of one per message."""
    out = attack(FOXGLOVE_LOG_LEVEL="DEBUG")
    sdk = [r for r in out["records"] if r["name"].startswith(SDK_PREFIXES)]
    assert sdk, "the SDK forwarded nothing: did FOXGLOVE_LOG_LEVEL stop working?"
    unfiltered = {r["name"] for r in sdk if not r["filtered"]}
    assert not unfiltered, f"SDK loggers without the filter (add to SDK_LOGGERS): {unfiltered}"
    for r in out["records"]:
        text = r["text"]
        assert not any(ord(c) < 32 for c in text), text[:200]
        assert not text.startswith("ERROR rig.service"), text[:200]
    for r in sdk:
        assert len(r["text"].split(" [foxglove SDK: ")[0]) <= MAX_CHARS + 40
    windows = math.ceil(out["elapsed_s"] / WINDOW_S) + 2
    assert len(sdk) <= (GLOBAL_BURST + 1) * windows + 20
    assert len(sdk) < FLOOD / 10
    assert any("more" in r["text"] and "not logged" in r["text"] for r in out["records"])
    invalid = [r for r in sdk if r["text"].startswith("Invalid message from")]
    unknown = [r for r in sdk if "unknown channel" in r["text"]]
    assert len(invalid) <= (BURST + 1) * windows and len(unknown) <= (BURST + 1) * windows
    assert len(unknown) < UNKNOWN / 100
    assert out["served"] and out["state"] == "stopped"


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def run(filt: ClientTextFilter, texts: list[str], name: str = SDK_LOGGERS[6]
        ) -> list[logging.LogRecord]:
    passed = []
    for text in texts:
        rec = logging.LogRecord(name, logging.ERROR, __file__, 1, "%s", (text,), None)
        if filt.filter(rec):
            passed.append(rec)
    return passed


def test_flood_passes_a_burst_then_one_summary() -> None:
    clock = Clock()
    filt = ClientTextFilter(clock)
    flood = ["Invalid message from 127.0.0.1:40000: EOF while parsing"] * 5000
    assert len(run(filt, flood)) == BURST
    clock.t += WINDOW_S
    passed = run(filt, flood[:1])
    assert len(passed) == 1
    msg = passed[0].getMessage()
    assert (f"{5000 - BURST} more 'Invalid message from CLIENT' records from client "
            "127.0.0.1:40000 in 1.0 s, not logged") in msg
    # another client is limited on its own, the first one's summary is not repeated
    assert len(run(filt, ["Invalid message from 127.0.0.1:40001: x"] * 10)) == BURST - 0


def test_unknown_subscriptions_are_a_burst_and_the_rest_counted() -> None:
    filt = ClientTextFilter(Clock())
    texts = [f"Client 127.0.0.1:5 attempted to subscribe to unknown channel: {i}"
             for i in range(10_000)]
    assert len(run(filt, texts)) == BURST
    assert filt.suppressed_total == 10_000 - BURST


def test_newlines_and_long_op_names_are_escaped_and_capped() -> None:
    filt = ClientTextFilter(Clock())
    forged = f"Invalid message from 127.0.0.1:7: unknown variant `a\n{FAKE_LINE}\r\x1b[2J`"
    long = "Invalid message from 127.0.0.1:8: unknown variant `" + "x" * 100_000 + "`"
    a, b = run(filt, [forged, long])
    assert "\n" not in a.getMessage() and "\\n" + FAKE_LINE in a.getMessage()
    assert "\x1b" not in a.getMessage() and a.args is None
    assert len(b.getMessage()) <= MAX_CHARS + 40 and "more characters" in b.getMessage()


def test_many_clients_share_a_global_budget_and_bounded_memory() -> None:
    filt = ClientTextFilter(Clock())
    texts = [f"Invalid message from 10.0.{i // 250}.{i % 250}:1: x" for i in range(5000)]
    assert len(run(filt, texts)) == GLOBAL_BURST
    assert len(filt._counts) <= 257


def test_flush_logs_what_the_window_held_back(caplog: pytest.LogCaptureFixture) -> None:
    filt = ClientTextFilter(Clock())
    run(filt, ["Invalid message from 127.0.0.1:9: x"] * 50)
    log = logging.getLogger("rig.foxglove_server")
    with caplog.at_level(logging.WARNING, logger="rig.foxglove_server"):
        filt.flush(log)
        filt.flush(log)        # nothing more held back: no second line
    assert len(caplog.records) == 1 and "47 more" in caplog.records[0].getMessage()


def test_attacked_demo_logs_a_few_escaped_lines_and_runs_without_fault() -> None:
    """``rig demo --timing lockstep --foxglove PORT`` with the SDK forwarding its ERROR
    records (FOXGLOVE_LOG_LEVEL=ERROR) attacked by a real client: the demo's stderr (its
    log) holds a few escaped, capped SDK lines and a summary instead of one per message,
    no forged line of its own, and the run ends without a fault with every tick run."""
    from tests.support.foxglove_attack import FORGED
    from tests.support.foxglove_demo import SUBPROTOCOLS, connect_when_up, free_port
    from tests.support.foxglove_demo import demo as start_demo

    port = free_port()
    os.environ["FOXGLOVE_LOG_LEVEL"] = "ERROR"      # inherited by the demo only
    try:
        proc = start_demo("--duration", "4", "--timing", "lockstep", "--no-record",
                          "--foxglove", f"127.0.0.1:{port}")
    finally:
        del os.environ["FOXGLOVE_LOG_LEVEL"]
    try:
        try:
            with connect_when_up(f"ws://127.0.0.1:{port}", proc) as ws:
                assert ws.subprotocol in SUBPROTOCOLS
                junk = (["{"] * FLOOD
                        + [json.dumps({"op": f"sub\n{FAKE_LINE}\n{i}"}) for i in range(FORGED)]
                        + [json.dumps({"op": "x" * 100_000})]
                        + [json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": i, "channelId": 900_000 + i} for i in range(UNKNOWN)]})])
                for m in junk:
                    ws.send(m)
        except ConnectionClosed:    # the viewer may drop the attacker before a close frame
            pass                    # (on a busy machine): what is checked is the demo's log
        out, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    lines = err.splitlines()
    sdk = [ln for ln in lines if ln.split(" ", 2)[1:2] and
           ln.split(" ", 2)[1].startswith(SDK_PREFIXES)]
    assert not any(ln.startswith("ERROR rig.service") for ln in lines), err[-3000:]
    assert all(len(ln) <= MAX_CHARS + 400 for ln in sdk)
    assert 0 < len(sdk) < 100, "\n".join(sdk[:20])
    assert any("not logged" in ln for ln in lines), "\n".join(sdk[:20])
    summary = json.loads(out)
    assert summary["faults"] == [], summary["faults"]
    assert summary["foxglove"]["state"] == "stopped"
    assert summary["timing"]["ticks"] >= 4 * 1000 * 0.9
