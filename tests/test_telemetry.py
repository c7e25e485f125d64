"""Zenoh telemetry: loopback-only sessions, multicast scouting off, explicit ports."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from controller.config import TelemetryConfig, default_config
from rig.telemetry import COMMANDS, TelemetryPublisher, validate_command, zenoh_config

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(120)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def tcfg(port: int, **kw: Any) -> TelemetryConfig:
    base = default_config().telemetry
    return replace(base, endpoints=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False, **kw)


def client_session(port: int) -> zenoh.Session:
    """A second, independent session connecting to the publisher (no listener)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def snapshot(k: int) -> dict[str, Any]:
    return {
        "tick": k, "t_ns": k * 20_000_000, "lifecycle": "ACTIVE" if k >= 3 else "INACTIVE",
        "fault": None,
        "state": {"rattlespace_m": 0.001 * k, "q": np.array([0.5, 1.5 * k]),
                  "firing_weight": [0.25, 0.75], "force_ref_n": float("nan")},
        "timing": {"wake_late_s": 1e-5 * k, "dropped_recording": 0},
    }


def wait_for(pred: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


class Rig:
    """A publisher plus a record of the commands its handler saw."""

    def __init__(self, port: int, **kw: Any) -> None:
        self.commands: list[tuple[str, dict[str, Any]]] = []
        self.tp = TelemetryPublisher(tcfg(port, **kw), self.status, self.handle)

    def status(self) -> dict[str, Any]:
        return {"lifecycle": "INACTIVE", "fault": None, "tick": 42}

    def handle(self, name: str, args: dict[str, Any]) -> str:
        self.commands.append((name, args))
        if name == "disarm":
            raise ValueError("not armed")
        return f"queued {name}"


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def rig(port: int) -> Iterator[Rig]:
    r = Rig(port)
    assert r.tp.wait_connected(10), r.tp.error
    yield r
    r.tp.close()


def test_config_is_loopback_and_no_multicast(port: int) -> None:
    listen = zenoh_config(tcfg(port))
    assert json.loads(listen.get_json("listen/endpoints")) == [f"tcp/127.0.0.1:{port}"]
    assert json.loads(listen.get_json("scouting/multicast/enabled")) is False
    conn = zenoh_config(tcfg(port, listen=False, mode="client"))
    assert json.loads(conn.get_json("listen/endpoints")) == []
    assert json.loads(conn.get_json("connect/endpoints")) == [f"tcp/127.0.0.1:{port}"]
    assert json.loads(conn.get_json("mode")) == "client"
    d = default_config().telemetry
    assert d.endpoints == ["tcp/127.0.0.1:7447"] and not d.multicast_scouting
    assert not d.commands_enabled


def test_in_process_subscriber_receives_state(rig: Rig, port: int) -> None:
    s2 = client_session(port)
    got: dict[str, list[dict[str, Any]]] = {}
    lock = threading.Lock()

    def on(sample: zenoh.Sample) -> None:
        with lock:
            got.setdefault(str(sample.key_expr), []).append(json.loads(sample.payload.to_bytes()))

    sub = s2.declare_subscriber("rig/**", on)
    try:
        # publish until the subscriber has seen the route (first samples may race the link)
        k = 0
        while not wait_for(lambda: "rig/state" in got, 0.1) and k < 100:
            assert rig.tp.offer(snapshot(0))
            k += 1
        for k in range(1, 6):
            assert rig.tp.offer(snapshot(k))
        assert wait_for(lambda: any(m["tick"] == 5 for m in got.get("rig/state", [])))
        state = next(m for m in got["rig/state"] if m["tick"] == 5)
        assert state == {"tick": 5, "t_ns": 100_000_000, "rattlespace_m": 0.005,
                         "q": [0.5, 7.5], "firing_weight": [0.25, 0.75],
                         "force_ref_n": None, "nonfinite": ["force_ref_n"]}
        assert wait_for(lambda: any(m["tick"] == 5 for m in got.get("rig/timing", [])))
        timing = next(m for m in got["rig/timing"] if m["tick"] == 5)
        assert timing["wake_late_s"] == pytest.approx(5e-5)
        assert timing["dropped_telemetry"] == 0
        # lifecycle is published on change (tick 3 -> ACTIVE), not on every snapshot
        lc = [(m["tick"], m["lifecycle"]) for m in got["rig/lifecycle"]]
        assert (3, "ACTIVE") in lc and (4, "ACTIVE") not in lc
        assert all(m["fault"] is None for m in got["rig/fault"])
    finally:
        sub.undeclare()
        s2.close()


SUBSCRIBER = """
import json, sys, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"peer"')
c.insert_json5("listen/endpoints", "[]")
c.insert_json5("connect/endpoints", json.dumps(["tcp/127.0.0.1:%d"]))
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
sub = s.declare_subscriber("rig/state")
print("ready", flush=True)
for _ in range(3):
    sample = sub.recv()
    print(sample.payload.to_string(), flush=True)
s.close()
"""


def test_subprocess_subscriber_receives_state(rig: Rig, port: int) -> None:
    proc = subprocess.Popen([sys.executable, "-c", SUBSCRIBER % port],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        k = 0
        while proc.poll() is None and k < 2000:
            rig.tp.offer(snapshot(k))
            k += 1
            time.sleep(0.01)
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        msgs = [json.loads(line) for line in out.splitlines()]
        assert len(msgs) == 3
        for m in msgs:
            assert m["q"] == [0.5, 1.5 * m["tick"]]
            assert m["rattlespace_m"] == pytest.approx(0.001 * m["tick"])
    finally:
        if proc.poll() is None:
            proc.kill()  # our own child, by handle (PID)
            proc.wait()


def query(session: zenoh.Session, key: str, payload: str | None = None
          ) -> list[tuple[bool, dict[str, Any]]]:
    out = []
    for r in session.get(key, payload=payload, timeout=3.0):
        answer = r.ok if r.ok is not None else r.err
        assert answer is not None
        out.append((r.ok is not None, json.loads(answer.payload.to_bytes())))
    return out


def test_status_queryable_answers(rig: Rig, port: int) -> None:
    s2 = client_session(port)
    try:
        replies: list[tuple[bool, dict[str, Any]]] = []

        def answered() -> bool:
            replies.extend(query(s2, "rig/status"))
            return bool(replies)

        assert wait_for(answered)
        ok, body = replies[0]
        assert ok
        assert body["lifecycle"] == "INACTIVE" and body["tick"] == 42
        assert body["telemetry"]["commands_enabled"] is False
    finally:
        s2.close()


def test_commands_ignored_when_disabled(rig: Rig, port: int) -> None:
    s2 = client_session(port)
    try:
        assert wait_for(lambda: bool(query(s2, "rig/status")))  # link is up
        assert query(s2, "rig/cmd/arm") == []        # nobody answers
        s2.put("rig/cmd/arm", "{}")
        time.sleep(0.3)
        assert rig.commands == [] and rig.tp.commands_received == 0
    finally:
        s2.close()


def test_commands_handled_when_enabled(port: int) -> None:
    r = Rig(port, commands_enabled=True)
    assert r.tp.wait_connected(10), r.tp.error
    s2 = client_session(port)
    acks: list[dict[str, Any]] = []
    sub = s2.declare_subscriber("rig/ack/**",
                                lambda smp: acks.append(json.loads(smp.payload.to_bytes())))
    try:
        assert wait_for(lambda: bool(query(s2, "rig/status")))
        assert query(s2, "rig/cmd/arm") == [
            (True, {"command": "arm", "accepted": True, "result": "queued arm"})]
        assert query(s2, "rig/cmd/weight_set", '{"weight_set": 2}')[0][0]
        assert query(s2, "rig/cmd/blending", '{"blending": "bayes"}')[0][0]
        ok, body = query(s2, "rig/cmd/disarm")[0]      # handler rejects
        assert not ok and body["error"] == "not armed"
        ok, body = query(s2, "rig/cmd/self_destruct")[0]  # never reaches the handler
        assert not ok and "unknown command" in body["error"]
        ok, body = query(s2, "rig/cmd/weight_set", '{"weight_set": "2"}')[0]
        assert not ok and "must be int" in body["error"]
        ok, body = query(s2, "rig/cmd/arm", "not json")[0]
        assert not ok
        s2.put("rig/cmd/reset", "")
        assert wait_for(lambda: any(a["command"] == "reset" for a in acks))
        assert acks[-1] == {"command": "reset", "accepted": True, "result": "queued reset"}
        assert r.commands == [("arm", {}), ("weight_set", {"weight_set": 2}),
                              ("blending", {"blending": "bayes"}), ("disarm", {}),
                              ("reset", {})]
    finally:
        sub.undeclare()
        s2.close()
        r.tp.close()


def test_offer_never_blocks_when_network_down_and_queue_full(port: int) -> None:
    # client mode towards a port nobody listens on: the session cannot open, the queue
    # is never drained, offers must still return at once and count drops.
    cfg = tcfg(port, mode="client", listen=False, queue_size=8)
    tp = TelemetryPublisher(cfg, dict, None, retry_s=0.05)
    try:
        t0 = time.perf_counter()
        results = [tp.offer(snapshot(k)) for k in range(5000)]
        elapsed = time.perf_counter() - t0
        assert results[:8] == [True] * 8 and not any(results[8:])
        assert tp.dropped == 5000 - 8
        assert elapsed < 2.0   # generous: ~1 us per offer; a blocking put would hang
        assert wait_for(lambda: tp.error is not None, 5)
        assert not tp.connected
    finally:
        tp.close()
    assert not tp.offer(snapshot(0))      # closed: dropped, not blocked
    assert tp.dropped == 5000 - 8 + 1


def test_due_decimates_to_rate(port: int) -> None:
    tp = TelemetryPublisher(tcfg(port, rate_hz=50.0, mode="client", listen=False), dict,
                            retry_s=10.0)
    try:
        ticks = [k for k in range(1000) if tp.due(k * 1_000_000)]   # 1 s of 1 kHz
        assert ticks == list(range(0, 1000, 20))
    finally:
        tp.close()


_arg = st.one_of(st.integers(), st.text(max_size=5), st.booleans(), st.none(), st.floats())


@given(name=st.one_of(st.sampled_from(sorted(COMMANDS)), st.text(max_size=8)),
       args=st.one_of(st.dictionaries(st.sampled_from(
           ["weight_set", "blending", "x", "speed_mps", "roughness_gd"]), _arg, max_size=3),
           _arg))
def test_validate_command_property(name: str, args: Any) -> None:
    expected_ok = (
        isinstance(args, dict)
        and (
            (name in ("arm", "disarm", "reset") and args == {})
            or (name == "weight_set" and list(args) == ["weight_set"]
                and type(args["weight_set"]) is int)
            or (name == "blending" and list(args) == ["blending"]
                and type(args["blending"]) in (int, str))
            or (name == "road" and sorted(args) == ["roughness_gd", "speed_mps"]
                and all(type(v) is int or (type(v) is float and v - v == 0)
                        for v in args.values()))
        )
    )
    try:
        validate_command(name, args)
        ok = True
    except ValueError:
        ok = False
    assert ok == expected_ok


def test_deploy_zenoh_configs_load() -> None:
    """The json5 files shipped for a rig network (TLS, access control) are valid Zenoh
    configs and keep multicast scouting off."""
    files = sorted((ROOT / "deploy" / "zenoh").glob("*.json5"))
    assert files
    for f in files:
        conf = zenoh.Config.from_file(str(f))
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
        cfg = replace(default_config().telemetry, zenoh_config_file=str(f))
        merged = zenoh_config(cfg)
        assert json.loads(merged.get_json("listen/endpoints")) == cfg.endpoints


CERTS = """
set -e
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -keyout ca.key \
  -out ca.pem -days 2 -subj "/CN=rig-test-ca" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
for cn in rig-service rig-operator rig-viewer; do
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -keyout $cn.key \
    -out $cn.csr -subj "/CN=$cn"
  printf "subjectAltName=IP:127.0.0.1\\nbasicConstraints=CA:FALSE\\nkeyUsage=digitalSignature\\n\
extendedKeyUsage=serverAuth,clientAuth\\n" > $cn.ext
  openssl x509 -req -in $cn.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out $cn.pem \
    -days 2 -extfile $cn.ext
done
"""


def tls_client(port: int, certs: Path, cn: str | None) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(certs / "ca.pem")))
    if cn is not None:
        c.insert_json5("transport/link/tls/enable_mtls", "true")
        c.insert_json5("transport/link/tls/connect_certificate", json.dumps(f"{certs}/{cn}.pem"))
        c.insert_json5("transport/link/tls/connect_private_key", json.dumps(f"{certs}/{cn}.key"))
    return zenoh.open(c)


@pytest.mark.skipif(subprocess.run(["which", "openssl"], capture_output=True).returncode != 0,
                    reason="openssl not installed (needed to make test certificates)")
def test_tls_and_access_control_from_deploy_config(tmp_path: Path, port: int) -> None:
    """deploy/zenoh/rig-tls-acl.json5 as shipped (paths and interface adapted): mTLS keeps
    certificate-less clients out, viewers get telemetry, only operators can command."""
    subprocess.run(["bash", "-c", CERTS], cwd=tmp_path, check=True, capture_output=True)
    text = (ROOT / "deploy/zenoh/rig-tls-acl.json5").read_text()
    assert '"eth1"' in text and "/etc/rig/zenoh" in text
    conf = tmp_path / "rig.json5"
    conf.write_text(text.replace("/etc/rig/zenoh", str(tmp_path)).replace('"eth1"', '"lo"'))
    seen: list[str] = []

    def handler(name: str, args: dict[str, Any]) -> str:
        seen.append(name)
        return "queued"

    cfg = replace(tcfg(port, commands_enabled=True), endpoints=[f"tls/127.0.0.1:{port}"],
                  zenoh_config_file=str(conf))
    tp = TelemetryPublisher(cfg, lambda: {"lifecycle": "INACTIVE"}, handler)
    try:
        assert tp.wait_connected(10), tp.error
        results = {}
        for cn in ("rig-operator", "rig-viewer", None):
            s2 = tls_client(port, tmp_path, cn)
            got: list[int] = []

            def on_state(smp: zenoh.Sample, got: list[int] = got) -> None:
                got.append(json.loads(smp.payload.to_bytes())["tick"])

            def status_ok(s2: zenoh.Session = s2) -> bool:
                return bool(query(s2, "rig/status"))

            def all_three(got: list[int] = got) -> bool:
                return len(got) == 3

            sub = s2.declare_subscriber("rig/state", on_state)
            try:
                connected = wait_for(status_ok, 3)
                for k in range(3):
                    tp.offer({"tick": k, "t_ns": k, "state": {"k": k}})
                    time.sleep(0.05)
                wait_for(all_three, 2 if connected else 0.3)
                results[cn] = (connected, len(got), query(s2, "rig/cmd/arm"))
            finally:
                sub.undeclare()
                s2.close()
        ok_reply = [(True, {"command": "arm", "accepted": True, "result": "queued"})]
        assert results["rig-operator"] == (True, 3, ok_reply)
        assert results["rig-viewer"] == (True, 3, [])        # denied by the ACL
        assert results[None] == (False, 0, [])                # no certificate: no link
        assert seen == ["arm"]
    finally:
        tp.close()
