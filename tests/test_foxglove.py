"""The live Foxglove view (rig/foxglove_server.py, docs/foxglove.md).

Must show: ``rig demo --foxglove 127.0.0.1:PORT`` serves the recording's channels over
the ``foxglove.websocket.v1`` protocol; a client sees them advertised, subscribes and
receives messages that validate against the advertised JSON Schemas (checked with the
``jsonschema`` package, not with project code); the recording of the same run has the
``foxglove.Log`` channel; a client sending garbage does not disturb the run; a port in
use is one line and the run goes on without the view.
"""

from __future__ import annotations

import itertools
import json
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from mcap.reader import make_reader
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from controller.config import ConfigError, default_config, parse_config
from rig.argtypes import foxglove_address
from rig.recording.scene import scene_messages
from rig.recording.schema import (
    LOG_SCHEMA,
    NONFINITE_NUMBER,
    TOPIC_EVENTS,
    TOPIC_INTERNALS,
    TOPIC_LOG,
    TOPIC_SCENE,
    TOPIC_SIGNALS,
    TOPIC_TF,
    TOPIC_TIMING,
    TOPICS,
    LogLevel,
    log_message,
)
from tests.support.foxglove_demo import (
    SUBPROTOCOLS,
    connect_when_up,
    demo,
    free_port,
)

ROOT = Path(__file__).resolve().parents[1]
MUST_ADVERTISE = {TOPIC_SIGNALS, TOPIC_INTERNALS, TOPIC_TIMING, TOPIC_LOG}


def message_data(frame: bytes) -> tuple[int, int, bytes]:
    """foxglove.websocket.v1 binary MessageData: op 0x01, subscription u32, time u64."""
    assert frame[0] == 0x01, frame[:1]
    sub, t_ns = struct.unpack_from("<IQ", frame, 1)
    return sub, t_ns, frame[13:]


def send_garbage(ws: ClientConnection) -> None:
    """Text that is no JSON, a subscription to a channel that does not exist, operations
    the server does not offer, a binary frame of an unknown opcode."""
    for junk in ("not json", '{"op": "subscribe", "subscriptions": [{"id": 1, '
                 '"channelId": 987654}]}', '{"op": "advertise", "channels": 5}',
                 '{"op": "setParameters", "parameters": []}', '{"op": 7}',
                 b"\x02\xff\xff\xff\xff" + os.urandom(64)):
        try:
            ws.send(junk)
        except ConnectionClosed:
            return


def validator(schema_text: str) -> jsonschema.protocols.Validator:
    schema = json.loads(schema_text)
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)  # type: ignore[no-any-return]


@pytest.mark.slow
def test_live_view_serves_the_recording_channels(tmp_path: Path) -> None:
    port = free_port()
    rec = tmp_path / "live.mcap"
    proc = demo("--duration", "8", "--foxglove", f"127.0.0.1:{port}", "--record", str(rec))
    try:
        with connect_when_up(f"ws://127.0.0.1:{port}", proc) as ws:
            assert ws.subprotocol in SUBPROTOCOLS
            channels: dict[int, dict[str, Any]] = {}
            server_info = None
            end = time.monotonic() + 10
            while not {c["topic"] for c in channels.values()} >= MUST_ADVERTISE:
                assert time.monotonic() < end, f"advertised only {channels}"
                msg = json.loads(ws.recv(timeout=5))
                if msg["op"] == "serverInfo":
                    server_info = msg
                elif msg["op"] == "advertise":
                    channels.update({c["id"]: c for c in msg["channels"]})
            assert server_info is not None
            # clients may only subscribe: no publishing, parameters or services offered
            assert not {"clientPublish", "parameters", "services"} & set(
                server_info.get("capabilities", []))
            by_topic = {c["topic"]: c for c in channels.values()}
            for topic, ch in by_topic.items():
                assert ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
                assert json.loads(ch["schema"]) == TOPICS[topic], topic   # the recording's
            assert by_topic[TOPIC_LOG]["schemaName"] == "foxglove.Log"
            assert by_topic[TOPIC_SCENE]["schemaName"] == "foxglove.SceneUpdate"
            assert by_topic[TOPIC_TF]["schemaName"] == "foxglove.FrameTransform"
            subs = {i: c for i, c in enumerate(channels.values())}
            validators = {i: validator(c["schema"]) for i, c in subs.items()}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": c["id"]} for i, c in subs.items()]}))

            # a second client sends garbage, subscribes to channels that do not exist and
            # asks for things the server does not offer
            with connect(f"ws://127.0.0.1:{port}",
                         subprotocols=SUBPROTOCOLS) as bad:  # type: ignore[arg-type]
                send_garbage(bad)

            seen: dict[str, int] = {}
            lifecycle_logs: list[dict[str, Any]] = []
            last: dict[str, Any] = {}
            while proc.poll() is None:
                try:
                    frame = ws.recv(timeout=2)
                except (TimeoutError, ConnectionClosed):
                    break
                if isinstance(frame, str):
                    continue
                sub, t_ns, payload = message_data(frame)
                topic = subs[sub]["topic"]
                msg = json.loads(payload)
                validators[sub].validate(msg)
                seen[topic] = seen.get(topic, 0) + 1
                last[topic] = msg
                if topic == TOPIC_LOG:
                    lifecycle_logs.append(msg)
                assert t_ns > 1_600_000_000 * 10**9     # wall time, like the recording
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert {TOPIC_SIGNALS, TOPIC_INTERNALS, TOPIC_TIMING, TOPIC_SCENE, TOPIC_TF,
            TOPIC_LOG, TOPIC_EVENTS} <= set(seen), seen
    assert seen[TOPIC_SIGNALS] > 100                   # 100 Hz for several seconds
    n_models = len(last[TOPIC_INTERNALS]["firing_weight"])
    assert n_models >= 2 and len(last[TOPIC_INTERNALS]["q"]) == n_models
    assert len(last[TOPIC_INTERNALS]["probability"]) == n_models
    assert any("ACTIVE" in m["message"] for m in lifecycle_logs), lifecycle_logs
    summary = json.loads(out)
    assert summary["foxglove"]["state"] == "stopped" and summary["foxglove"]["error"] is None
    assert summary["foxglove"]["dropped"] == 0
    assert summary["armed_at_s"] is not None
    # the garbage did not reach the loop: no fault, no exception, every tick ran
    assert summary["faults"] == [] or all(f["code"] != "EXCEPTION" for f in summary["faults"])
    assert summary["timing"]["ticks"] >= 8 * 1000 * 0.9

    # the recording of the same run has the foxglove.Log channel and the 3D picture
    with rec.open("rb") as f:
        reader = make_reader(f)
        summ = reader.get_summary()
        assert summ is not None
        topics = {c.topic: summ.schemas[c.schema_id] for c in summ.channels.values()}
        assert topics[TOPIC_LOG].name == "foxglove.Log"
        assert topics[TOPIC_SCENE].name == "foxglove.SceneUpdate"
        assert topics[TOPIC_TF].name == "foxglove.FrameTransform"
        log_check = validator(topics[TOPIC_LOG].data.decode())
        logs = []
        for _, channel, message in reader.iter_messages(topics=[TOPIC_LOG, TOPIC_TF]):
            msg = json.loads(message.data)
            if channel.topic == TOPIC_LOG:
                log_check.validate(msg)
                logs.append(msg)
    assert any(m["level"] == LogLevel.INFO and m["file"] == "ACTIVE" for m in logs), logs


@pytest.mark.slow
def test_port_in_use_is_one_line_and_control_goes_on() -> None:
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        proc = demo("--duration", "2", "--no-record", "--foxglove", str(port))
        out, err = proc.communicate(timeout=180)
    assert proc.returncode == 0, err
    lines = [ln for ln in err.splitlines() if "foxglove" in ln.lower()]
    assert len(lines) == 1, err
    assert f"127.0.0.1:{port}" in lines[0] and "control goes on" in lines[0]
    summary = json.loads(out)
    fg = summary["foxglove"]
    assert fg["state"] == "failed" and "\n" not in fg["error"]
    assert summary["timing"]["ticks"] >= 2 * 1000 * 0.9          # control went on


def test_bad_address_is_refused_in_one_line() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for bad, word in (("localhost:80x", "port"), ("1.2.3:9000", "IP address"),
                      ("99999", "port")):
        res = subprocess.run([sys.executable, "-m", "rig.cli", "demo", "--foxglove", bad],
                             cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
        assert res.returncode == 2
        assert res.stderr.count("\n") == 1 and word in res.stderr, res.stderr
    assert foxglove_address("8765") == ("127.0.0.1", 8765)
    assert foxglove_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert foxglove_address("[::1]:9000") == ("::1", 9000)


def test_config_section_is_validated() -> None:
    assert default_config().foxglove.enabled is False
    for data, key in (({"foxglove": {"host": "rig.local"}}, "foxglove.host"),
                      ({"foxglove": {"port": 70000}}, "foxglove.port"),
                      ({"foxglove": {"rate_hz": 5000.0}}, "foxglove.rate_hz"),
                      ({"foxglove": {"queue_size": 0}}, "foxglove.queue_size")):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            parse_config(data)


def test_log_levels_follow_severity() -> None:
    check = validator(json.dumps(LOG_SCHEMA))
    fault = log_message(5 * 10**18, 10, "fault", {
        "from": "ACTIVE", "to": "FAULT", "reason": "x", "fault": "SENSOR_STALE"})
    arm = log_message(1, 3, "lifecycle", {"from": "INACTIVE", "to": "ACTIVE",
                                          "reason": "armed", "fault": "NONE"})
    refused = log_message(1, 3, "command", {"command": "arm", "argument": None,
                                            "accepted": False, "message": "warming up"})
    bus = log_message(1, 3, "note", {"bus_exception": "send", "type": "CanError",
                                     "error": "boom", "errno": None})
    for msg in (fault, arm, refused, bus, log_message(1, 0, "note", "text")):
        check.validate(msg)
    assert fault["level"] == LogLevel.ERROR and "could no longer see the rig" in fault["message"]
    assert fault["timestamp"] == {"sec": 5 * 10**9, "nsec": 0} and fault["line"] == 10
    assert arm["level"] == LogLevel.INFO and arm["file"] == "ACTIVE"
    assert refused["level"] == LogLevel.WARNING and bus["level"] == LogLevel.WARNING


def test_scene_moves_with_rattlespace() -> None:
    tf_check = validator(json.dumps(TOPICS[TOPIC_TF]))
    scene_check = validator(json.dumps(TOPICS[TOPIC_SCENE]))
    tf0, scene0 = scene_messages(10**18, 0.0, 0.0, "INACTIVE")
    tf1, scene1 = scene_messages(10**18, 0.02, 1500.0, "ACTIVE")
    tf_nan, scene_nan = scene_messages(10**18, float("nan"), None, "FAULT")
    for tf, scene in ((tf0, scene0), (tf1, scene1), (tf_nan, scene_nan)):
        tf_check.validate(tf)
        scene_check.validate(scene)
    # compression (positive rattlespace) brings the body 20 mm down
    assert tf0["translation"]["z"] - tf1["translation"]["z"] == pytest.approx(0.02)
    assert tf_nan["translation"] == tf0["translation"]
    ids = [e["id"] for e in scene1["entities"]]
    assert {"road", "wheel", "body", "actuator"} <= set(ids)


def test_layout_uses_the_recording_channel_names() -> None:
    """Every plotted path of deploy/foxglove/rig-layout.json names a channel and a field
    of rig.recording.schema (or the layout's own script), so the layout works on a
    recording and live alike."""
    layout = json.loads((ROOT / "deploy/foxglove/rig-layout.json").read_text())
    scripts = {}
    for node in layout["userNodes"].values():
        src = node["sourceCode"]
        out = src.split('export const output = "')[1].split('"')[0]
        inputs = json.loads(src.split("export const inputs = ")[1].split(";")[0])
        assert set(inputs) <= set(TOPICS)
        scripts[out] = src
    panels = layout["configById"]
    used: set[str] = set()
    for panel_id, conf in panels.items():
        for p in conf.get("paths", []):
            topic, _, field = p["value"].partition(".")
            field = field.split("[")[0]
            used.add(topic)
            if topic in scripts:
                assert f"{field}:" in scripts[topic], (panel_id, p["value"])
            else:
                assert field in TOPICS[topic]["properties"], (panel_id, p["value"])
        if "topicToRender" in conf:
            used.add(conf["topicToRender"])
        used |= set(conf.get("topics", {}))
    assert {TOPIC_SIGNALS, TOPIC_INTERNALS, TOPIC_LOG, TOPIC_SCENE} <= used
    assert panels["RosOut!log"]["topicToRender"] == TOPIC_LOG
    # the controller's estimates are plotted; the runtime's tire estimate is written as
    # NONFINITE_NUMBER until it has one: its plot's fixed y range keeps that off the
    # chart and holds the stiffness scales and the fit's band (5-20 Hz)
    plotted = {p["value"]: panel_id for panel_id, conf in panels.items()
               for p in conf.get("paths", [])}
    for key in ("sprung_mass_est_kg", "spring_rate_est_n_per_m", "damping_est_ns_per_m",
                "wheel_hop_hz", "tire_stiffness_est"):
        assert f"{TOPIC_INTERNALS}.{key}" in plotted, key
    tire = panels[plotted[f"{TOPIC_INTERNALS}.tire_stiffness_est"]]
    assert plotted[f"{TOPIC_INTERNALS}.wheel_hop_hz"] == plotted[
        f"{TOPIC_INTERNALS}.tire_stiffness_est"]
    assert NONFINITE_NUMBER < tire["minYValue"] <= 0.0 and tire["maxYValue"] >= 20.0

    def leaves(node: Any) -> set[str]:
        if isinstance(node, str):
            return {node}
        return leaves(node["first"]) | leaves(node["second"])

    assert leaves(layout["layout"]) == set(panels)       # every panel is placed


def test_a_stalled_publisher_drops_and_counts_without_blocking_the_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The publisher thread hangs (as if the SDK or a client held it): the loop's hand-off
    still returns at once, the queue keeps at most queue_size items and the rest are
    dropped and counted."""
    import operator
    import threading

    import numpy as np

    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design
    from rig.foxglove_server import FoxgloveView
    from rig.service.loop import TICK_RECORD_FIELDS, tick_record_layout

    cfg = default_config().replace(foxglove={"enabled": True, "port": 0, "queue_size": 8})
    rt = BankRuntime(cached_design(cfg), cfg=cfg)
    release = threading.Event()
    monkeypatch.setattr(FoxgloveView, "_publish_tick",
                        lambda self, item: release.wait(30))
    view = FoxgloveView(cfg.foxglove, tick_record_layout(rt))
    try:
        assert view.state == "serving" and view.port > 0
        layout = tick_record_layout(rt)
        n_scalars = len(layout.scalar_fields)
        scalars = [0] * n_scalars
        arrays = [operator.attrgetter(src.removeprefix("rt."))(rt)
                  for _key, kind, src in TICK_RECORD_FIELDS if kind == "array"]
        view.offer_tick(0, scalars, arrays)
        end = time.monotonic() + 10
        while view._queue.qsize() and time.monotonic() < end:   # the thread takes it, hangs
            time.sleep(0.01)
        worst = 0
        for k in range(1, 200):
            t0 = time.perf_counter_ns()
            view.offer_tick(k, [k, *scalars[1:]], arrays)
            worst = max(worst, time.perf_counter_ns() - t0)
        assert view.offer_event(0, 0, "note", "x") is False    # full: dropped too
        # one item is held by the hung thread, queue_size wait, the rest were dropped
        assert view.dropped == 200 + 1 - 8 - 1
        assert worst < 5_000_000                                # never waited (5 ms)
        assert np.isfinite(worst)
    finally:
        release.set()
        view.close()
    assert view.state == "stopped"


def test_scene_period_is_an_absolute_grid() -> None:
    """Ticks offered every 10 ms, each 4 ms late: a picture every 50 ms (20 Hz), not
    every 60 ms as when the period was counted from the (late) drawing tick."""
    from rig.recording.scene import SCENE_PERIOD_NS, next_scene_ns

    deadline: int | None = None
    drawn = []
    for k in range(101):
        t_ns = k * 10_000_000 + 4_000_000
        if deadline is None or t_ns >= deadline:
            deadline = next_scene_ns(deadline, t_ns)
            drawn.append(t_ns)
    gaps = {b - a for a, b in itertools.pairwise(drawn)}
    assert gaps == {SCENE_PERIOD_NS} and len(drawn) == 21
    assert next_scene_ns(0, 500_000_000) == 550_000_000    # after a long gap: from now
