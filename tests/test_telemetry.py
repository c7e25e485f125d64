"""Zenoh telemetry: loopback-only sessions, multicast scouting off, explicit ports."""

from __future__ import annotations

import json
import logging
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
from rig.operator_commands import OPERATOR_COMMANDS as COMMANDS
from rig.operator_commands import validate_command
from rig.telemetry import TelemetryPublisher, zenoh_config
from tests.support.stepped_service import SteppedService
from tests.support.zenoh_client import client_session, free_port, query, wait_for

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(120)



def tcfg(port: int, **kw: Any) -> TelemetryConfig:
    base = default_config().telemetry
    return replace(base, endpoints=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False, **kw)



def snapshot(k: int) -> dict[str, Any]:
    return {
        "tick": k, "t_ns": k * 20_000_000, "lifecycle": "ACTIVE" if k >= 3 else "INACTIVE",
        "fault": None,
        "state": {"rattlespace_m": 0.001 * k, "q": np.array([0.5, 1.5 * k]),
                  "firing_weight": [0.25, 0.75], "force_ref_n": float("nan")},
        "timing": {"wake_late_s": 1e-5 * k, "dropped_recording": 0},
    }



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


def acl_publisher(tmp_path: Path, port: int) -> tuple[TelemetryPublisher, list[str]]:
    """The rig's publisher with deploy/zenoh/rig-tls-acl.json5 as shipped (certificates
    made in ``tmp_path``, interface ``lo``); returns it and the commands it handled."""
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
    return TelemetryPublisher(cfg, lambda: {"lifecycle": "INACTIVE"}, handler), seen


@pytest.mark.skipif(subprocess.run(["which", "openssl"], capture_output=True).returncode != 0,
                    reason="openssl not installed (needed to make test certificates)")
def test_tls_and_access_control_from_deploy_config(tmp_path: Path, port: int) -> None:
    """deploy/zenoh/rig-tls-acl.json5 as shipped (paths and interface adapted): mTLS keeps
    certificate-less clients out, viewers get telemetry, only operators can command."""
    tp, seen = acl_publisher(tmp_path, port)
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


# ---------------------------------------------------------------------------- hardening


def _peer_config(listen: list[str], connect: list[str], **keys: Any) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    c.insert_json5("scouting/multicast/enabled", "false")
    for key, value in keys.items():
        c.insert_json5(key.replace("__", "/"), json.dumps(value))
    return c


def _zids(session: zenoh.Session) -> set[str]:
    return {str(z) for z in session.info.peers_zid()}


_RIG_ZID = "f0f0f0f0f0f0f0f0"     # above the advertised peer's: the rig's side would dial


def test_session_config_turns_gossip_and_autoconnect_off(tmp_path: Path, port: int) -> None:
    """Whatever the json5 file says, the rig's session scouts no peers and dials none."""
    f = tmp_path / "z.json5"
    f.write_text('{ scouting: { gossip: { enabled: true, autoconnect: { peer: ["router", '
                 '"peer"] } }, multicast: { autoconnect: { peer: ["router", "peer"] } } } }')
    conf = zenoh_config(replace(tcfg(port), zenoh_config_file=str(f)))
    scouting = json.loads(conf.get_json("scouting"))
    assert scouting["gossip"]["enabled"] is False
    for how in ("gossip", "multicast"):
        assert scouting[how]["autoconnect"] == {"router": [], "peer": []}
    assert scouting["multicast"]["enabled"] is False


def test_rig_connects_only_to_configured_endpoints(tmp_path: Path) -> None:
    """A local peer B connected to the rig and to a peer C gossips C's locator: a Zenoh
    peer with gossip and autoconnect on (Zenoh's defaults) dials C on its own.  The rig's
    session must not.  The first half shows the scenario does make a default peer dial."""
    id_file = tmp_path / "id.json5"
    id_file.write_text(f'{{ id: "{_RIG_ZID}" }}')

    def scenario(open_rig: Callable[[int], Callable[[], None]], wait_s: float) -> bool:
        p_rig, p_c = free_port(), free_port()
        close_rig = open_rig(p_rig)
        c = zenoh.open(_peer_config([f"tcp/127.0.0.1:{p_c}"], [], id="1111111111111111",
                                    scouting__gossip__autoconnect={"peer": [], "router": []}))
        b = zenoh.open(_peer_config([], [f"tcp/127.0.0.1:{p_rig}", f"tcp/127.0.0.1:{p_c}"]))
        try:
            b_zid = str(b.info.zid())
            assert wait_for(lambda: b_zid in _zids(c), 10)
            return wait_for(lambda: _RIG_ZID in _zids(c), wait_s)
        finally:
            b.close()
            c.close()
            close_rig()

    def default_peer(p: int) -> Callable[[], None]:
        conf = _peer_config([f"tcp/127.0.0.1:{p}"], [], id=_RIG_ZID)
        s = zenoh.open(conf)
        return s.close

    def rig(p: int) -> Callable[[], None]:
        tp = TelemetryPublisher(replace(tcfg(p), zenoh_config_file=str(id_file)), dict)
        assert tp.wait_connected(10), tp.error
        assert tp._session is not None and str(tp._session.info.zid()) == _RIG_ZID
        return tp.close

    t0 = time.monotonic()
    assert scenario(default_peer, 20.0), "a default peer did not dial the gossiped peer"
    dialled_after = time.monotonic() - t0
    assert not scenario(rig, max(3.0, 3 * dialled_after))


def test_status_replies_on_the_concrete_key(port: int) -> None:
    r = Rig(port, commands_enabled=True)
    assert r.tp.wait_connected(10), r.tp.error
    s2 = client_session(port)
    try:
        assert wait_for(lambda: bool(query(s2, "rig/status")))
        for selector in ("rig/status", "rig/*", "rig/**", "**"):
            replies = list(s2.get(selector, timeout=3.0))
            assert len(replies) == 1, selector     # the status; the command queryable is quiet
            assert replies[0].ok is not None
            assert str(replies[0].ok.key_expr) == "rig/status", selector
        assert r.commands == []                    # a wildcard query is never a command
        reply = next(iter(s2.get("rig/cmd/reset", timeout=3.0)))
        assert reply.ok is not None and str(reply.ok.key_expr) == "rig/cmd/reset"
    finally:
        s2.close()
        r.tp.close()


def test_error_replies_are_short_and_never_echo_large_input(port: int) -> None:
    r = Rig(port, commands_enabled=True)
    assert r.tp.wait_connected(10), r.tp.error
    s2 = client_session(port)
    acks: list[bytes] = []
    sub = s2.declare_subscriber("rig/ack/**", lambda smp: acks.append(smp.payload.to_bytes()))
    big = "x" * 50_000
    try:
        assert wait_for(lambda: bool(query(s2, "rig/status")))
        cases = [
            ("rig/cmd/" + "n" * 5000, ""),                               # long name
            ("rig/cmd/blending", json.dumps({"blending": 1, big: 1})),    # too large
            ("rig/cmd/weight_set", json.dumps({"weight_set": "y" * 900})),  # wrong type
            ("rig/cmd/arm", json.dumps({"z" * 300: 1, "w" * 300: 2})),   # unknown keys
            ("rig/cmd/arm", json.dumps(["q" * 900])),                    # not an object
            ("rig/cmd/arm", "{" + "[" * 900),                            # not JSON
        ]
        for key, payload in cases:
            raw = list(s2.get(key, payload=payload, timeout=3.0))
            assert len(raw) == 1 and raw[0].err is not None, key[:40]
            body = raw[0].err.payload.to_bytes()
            assert len(body) < 400, (key[:40], body[:120])
            reply = json.loads(body)
            assert not reply["accepted"] and len(reply["error"]) <= 200
        assert f"{len(cases[1][1])} bytes, at most 1024" in json.loads(
            next(iter(s2.get(cases[1][0], payload=cases[1][1], timeout=3.0))).err
            .payload.to_bytes())["error"]
        s2.put("rig/cmd/" + "m" * 3000, "{}")
        assert wait_for(lambda: bool(acks))
        assert len(acks[0]) < 400 and json.loads(acks[0])["accepted"] is False
        assert r.commands == []
    finally:
        sub.undeclare()
        s2.close()
        r.tp.close()


@pytest.mark.parametrize("prefix", ["rig", "lab/rig-1", "a", "x_y/z.w", "été/1"])
def test_valid_key_prefixes_are_concrete_zenoh_keys(prefix: str) -> None:
    from controller.config import parse_config

    cfg = parse_config({"telemetry": {"key_prefix": prefix}}).telemetry
    for leaf in ("status", "state", "cmd/arm"):
        assert str(zenoh.KeyExpr(f"{cfg.key_prefix}/{leaf}")) == f"{prefix}/{leaf}"


@given(prefix=st.text(alphabet=st.sampled_from("ab/*$#? @-_.é"), max_size=10))
def test_key_prefix_validation_agrees_with_zenoh(prefix: str) -> None:
    """What the config accepts is a valid Zenoh key without wildcards; what Zenoh
    refuses, the config refuses (with the key named)."""
    from controller.config import ConfigError, parse_config

    try:
        parse_config({"telemetry": {"key_prefix": prefix}})
    except ConfigError as exc:
        assert exc.key == "telemetry.key_prefix"
        return
    ke = zenoh.KeyExpr(prefix)
    assert "*" not in prefix and "$" not in prefix and str(ke) == prefix


@pytest.mark.parametrize("endpoint", [
    "tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tls/rig.local:7447", "udp/192.0.2.10:7447",
    "quic/10.0.0.1:1", "ws/127.0.0.1:65535", "tcp/127.0.0.1:7447?iface=lo",
    "tcp/127.0.0.1:7447#so_sndbuf=65536", "unixsock-stream//run/rig/zenoh.sock"])
def test_valid_endpoints_are_accepted_by_zenoh(endpoint: str) -> None:
    from controller.config import parse_config

    cfg = parse_config({"telemetry": {"endpoints": [endpoint]}}).telemetry
    conf = zenoh_config(cfg)
    assert json.loads(conf.get_json("listen/endpoints")) == [endpoint]


def test_offer_drops_and_counts_after_giving_up(tmp_path: Path, port: int) -> None:
    cfg = replace(tcfg(port), zenoh_config_file=str(tmp_path / "missing.json5"))
    tp = TelemetryPublisher(cfg, dict)
    try:
        assert tp.wait_settled(10) and tp.failed
        assert not any(tp.offer(snapshot(k)) for k in range(10))
        assert tp.dropped == 10
    finally:
        tp.close()


def _busy_port() -> tuple[socket.socket, int]:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s, int(s.getsockname()[1])


@pytest.mark.parametrize("case", ["busy_port", "missing_file", "unusable_endpoint",
                                  "bad_json5"])
def test_a_failing_session_is_reported_and_given_up(case: str, tmp_path: Path,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    """Each failure: a log line, ``status()``, the state callback; a bounded number of
    attempts, then telemetry stops trying."""
    holder, busy = _busy_port()
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    cfg, expected = {
        "busy_port": (tcfg(busy), "Address already in use"),
        "missing_file": (replace(tcfg(free_port()), zenoh_config_file=str(tmp_path / "no.json5")),
                         f"zenoh_config_file {tmp_path / 'no.json5'}: No such file"),
        # well-formed, but its directory does not exist (a local socket: nothing is sent)
        "unusable_endpoint": (replace(tcfg(0), endpoints=[
            f"unixsock-stream/{tmp_path}/no-such-dir/rig.sock"]),
            "Can not create a new UnixSocketStream listener"),
        "bad_json5": (replace(tcfg(free_port()), zenoh_config_file=str(bad)),
                      f"zenoh_config_file {bad}"),
    }[case]
    states: list[tuple[str, str | None]] = []
    try:
        with caplog.at_level("WARNING", logger="rig.telemetry"):
            tp = TelemetryPublisher(cfg, dict, retry_s=0.05, session_attempts=3,
                                    on_state=lambda s, e: states.append((s, e)))
            try:
                assert tp.wait_settled(20)
                st_ = tp.status()
            finally:
                tp.close()
    finally:
        holder.close()
    assert st_["state"] == "failed" and expected in str(st_["error"]), st_
    assert ".rs:" not in str(st_["error"])                 # no Rust source locations
    retried = case in ("busy_port", "unusable_endpoint")
    assert st_["attempts"] == (3 if retried else 1)
    assert states[-1] == ("failed", st_["error"])
    assert [s for s, _ in states] == ["retrying"] * (2 if retried else 0) + ["failed"]
    errors = [r for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "telemetry off" in errors[0].getMessage()
    assert expected in errors[0].getMessage()


# ---------------------------------------------------------------------------- the service


def _stepped_service(port: int) -> SteppedService:
    cfg = default_config().replace(telemetry={
        "endpoints": [f"tcp/127.0.0.1:{port}"], "commands_enabled": True})
    return SteppedService(cfg)


def test_every_operator_command_end_to_end(port: int) -> None:
    """Every command of ``rig.telemetry.COMMANDS`` from a second Zenoh session through
    the service's handler into the running loop, accepted and refused."""
    rig = _stepped_service(port)
    svc, loop = rig.svc, rig.svc.loop
    s2 = client_session(port)

    def cmd(name: str, args: dict[str, Any] | None = None) -> tuple[bool, dict[str, Any]]:
        payload = None if args is None else json.dumps(args)
        got = query(s2, f"rig/cmd/{name}", payload)
        assert len(got) == 1, (name, got)
        return got[0]

    def status() -> dict[str, Any]:
        """A status reply (waiting out the per-peer rate limit of status queries)."""
        end = time.monotonic() + 10.0
        while True:
            got = query(s2, "rig/status")
            if (got and got[0][0]) or time.monotonic() > end:
                return got[0][1] if got else {}
            time.sleep(0.1)

    try:
        assert svc.telemetry.wait_connected(10), svc.telemetry.error
        assert wait_for(lambda: status().get("health") == "ok", 60), status()
        assert status()["telemetry"]["state"] == "connected"

        assert cmd("arm") == (True, {"command": "arm", "accepted": True, "result": "armed"})
        assert loop.lifecycle.state.name == "ACTIVE"
        ok, body = cmd("road", {"speed_mps": 20.0, "roughness_gd": 256e-6})
        assert not ok and body["error"] == "road: disarm first"
        ok, body = cmd("weight_set", {"weight_set": 2})
        assert not ok and body["error"] == "weight_set: disarm first"
        assert cmd("disarm")[0] and loop.lifecycle.state.name == "INACTIVE"

        ok, body = cmd("road", {"speed_mps": 20.0, "roughness_gd": 256e-6})
        assert ok, body
        speeds = rig.cfg.noise.speeds_mps
        rough = rig.cfg.noise.road_roughness_gd
        assert svc.runtime.noise_index == svc.design.noise_index(speeds.index(20.0),
                                                                 rough.index(256e-6))
        ok, body = cmd("road", {"speed_mps": 5, "roughness_gd": 16e-6})   # integers too
        assert ok and svc.runtime.noise_index == svc.design.noise_index(0, 0), body
        assert cmd("blending", {"blending": "bayes"}) == (
            True, {"command": "blending", "accepted": True, "result": "blending 1"})
        assert svc.runtime.blending == 1      # the status follows within STATUS_REFRESH_S
        assert wait_for(lambda: status().get("blending") == 1, 10), status()
        ok, body = cmd("blending", {"blending": "kalman"})
        assert not ok and "allowed lqg, fuzzy, bayes, moving" in body["error"]
        assert cmd("weight_set", {"weight_set": 2})[0] and loop.weight_set == 2
        ok, body = cmd("weight_set", {"weight_set": 99})
        assert not ok and body["error"].startswith("weight_set:")

        ok, body = cmd("reset")
        assert ok and body["result"] == "nothing to reset in INACTIVE"
        rig.late_ticks = 2 * rig.cfg.safety.overrun_streak     # an overrun streak
        assert wait_for(lambda: loop.lifecycle.state.name == "FAULT", 30)
        assert wait_for(lambda: status().get("fault") == "OVERRUN_STREAK", 10), status()
        ok, body = cmd("arm")
        assert not ok and body["error"] == "cannot arm from FAULT"
        assert wait_for(lambda: rig.late_ticks == 0 and loop.timing.overrun_streak == 0, 30)
        assert cmd("reset") == (True, {"command": "reset", "accepted": True,
                                       "result": "reset, cleared OVERRUN_STREAK"})
        reset_tick = loop.tick_count

        def warm_again() -> bool:     # a status built after the reset (it may be 0.2 s old)
            st = status()
            return st.get("tick", -1) > reset_tick and st.get("health") == "ok"

        assert wait_for(warm_again, 60), status()
        acks: list[dict[str, Any]] = []
        sub = s2.declare_subscriber("rig/ack/arm",
                                    lambda smp: acks.append(json.loads(smp.payload.to_bytes())))
        try:
            s2.put("rig/cmd/arm", "{}")                       # fire and forget
            assert wait_for(lambda: bool(acks), 30)
        finally:
            sub.undeclare()
        assert acks == [{"command": "arm", "accepted": True, "result": "armed"}]
        assert loop.lifecycle.state.name == "ACTIVE"
        names = [t.reason for t in loop.transitions]
        assert names.count("armed") == 2
        assert {"arm", "disarm", "reset", "weight_set", "blending", "road"} == set(COMMANDS)
    finally:
        s2.close()
        rig.close()


def test_service_reports_a_failed_session(tmp_path: Path) -> None:
    """status(), systemd STATUS= and the control loop going on."""
    import uuid

    from hil.sim.closed_loop import cached_design
    from rig.rt.sdnotify import SdNotifier
    from rig.service.runner import Service, ServiceOptions

    sock_path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    server.settimeout(5.0)
    cfg = default_config().replace(telemetry={
        "endpoints": [f"tcp/127.0.0.1:{free_port()}"],
        "zenoh_config_file": str(tmp_path / "missing.json5")})
    from controller.artifact import save_design

    design = tmp_path / "design.npz"
    save_design(cached_design(cfg), design)
    svc = Service(cfg, ServiceOptions(
        design_path=str(design), interface="virtual", channel=f"tf-{uuid.uuid4().hex}",
        recording=False, telemetry=True, realtime=None, install_signal_handlers=False,
        duration_s=0.3), notifier=SdNotifier.from_environment({"NOTIFY_SOCKET": sock_path}))
    try:
        assert svc.telemetry.wait_settled(10)
        st_ = svc.status()["telemetry"]
        assert st_["state"] == "failed" and "missing.json5" in st_["error"]
        assert svc.run() == 0
        assert svc.loop.tick_count > 0
        msgs = []
        with pytest.raises(TimeoutError):
            while True:
                msgs.append(server.recv(4096).decode())
                server.settimeout(0.5)
    finally:
        svc.close()
        server.close()
    status_lines = [m for m in msgs if "STATUS=" in m]
    assert status_lines and all("telemetry FAILED: zenoh_config_file" in m
                                for m in status_lines), msgs
    assert any(m.startswith("READY=1") for m in msgs)


def test_rig_run_json_reports_telemetry_failure(tmp_path: Path) -> None:
    holder, busy = _busy_port()
    conf = tmp_path / "rig.toml"
    conf.write_text(f'[telemetry]\nendpoints = ["tcp/127.0.0.1:{busy}"]\n')
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "rig.cli", "run", "--config", str(conf), "--interface",
             "virtual", "--channel", f"tel-json-{busy}", "--duration", "0.5", "--json",
             "--no-record", "--no-realtime"],
            cwd=ROOT, capture_output=True, text=True, timeout=120)
    finally:
        holder.close()
    assert proc.returncode == 0, proc.stderr
    status = json.loads(proc.stdout)
    tel = status["telemetry"]
    assert tel["state"] in ("retrying", "failed") and "Address already in use" in tel["error"]
    assert status["tick"] > 0
    assert "telemetry" in proc.stderr and "Address already in use" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.skipif(subprocess.run(["which", "openssl"], capture_output=True).returncode != 0,
                    reason="openssl not installed (needed to make test certificates)")
def test_acl_viewers_can_only_read(tmp_path: Path, port: int) -> None:
    """deploy/zenoh/rig-tls-acl.json5: a viewer can neither publish on the telemetry keys
    (spoofing state for other viewers or the rig), nor answer status queries, nor
    command; it still reads.  Viewer and operator connect as Zenoh clients, so
    everything between them goes through the rig's session and its access control."""
    tp, seen = acl_publisher(tmp_path, port)
    assert tp.wait_connected(10), tp.error
    assert tp._session is not None
    inside: list[tuple[str, bytes]] = []        # what reaches the rig's own session
    spy = tp._session.declare_subscriber(
        "rig/**", lambda smp: inside.append((str(smp.key_expr), smp.payload.to_bytes())))

    def client(cn: str) -> zenoh.Session:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("transport/link/tls/root_ca_certificate",
                       json.dumps(str(tmp_path / "ca.pem")))
        c.insert_json5("transport/link/tls/enable_mtls", "true")
        c.insert_json5("transport/link/tls/connect_certificate",
                       json.dumps(f"{tmp_path}/{cn}.pem"))
        c.insert_json5("transport/link/tls/connect_private_key",
                       json.dumps(f"{tmp_path}/{cn}.key"))
        return zenoh.open(c)

    operator, viewer = client("rig-operator"), client("rig-viewer")
    got: dict[str, list[Any]] = {"operator": [], "viewer": []}
    subs = [s.declare_subscriber(
        "rig/state", lambda smp, who=who: got[who].append(json.loads(smp.payload.to_bytes())))
        for who, s in (("operator", operator), ("viewer", viewer))]
    fake = viewer.declare_queryable(
        "rig/status", lambda q: q.reply("rig/status", '{"lifecycle": "SPOOFED"}'))
    try:
        assert wait_for(lambda: bool(query(operator, "rig/status")), 10)
        assert wait_for(lambda: bool(query(viewer, "rig/status")), 10)
        k = 0
        while not (got["operator"] and got["viewer"]) and k < 200:   # both read telemetry
            tp.offer({"tick": k, "t_ns": k, "state": {"k": k}})
            k += 1
            time.sleep(0.02)
        assert got["operator"] and got["viewer"]
        for _ in range(20):                  # the viewer tries to publish and command
            viewer.put("rig/state", json.dumps({"tick": -1, "spoofed": True}))
            viewer.put("rig/lifecycle", json.dumps({"tick": -1, "lifecycle": "SPOOFED"}))
            viewer.put("rig/cmd/arm", "{}")
            viewer.delete("rig/state")
            time.sleep(0.01)
        assert query(viewer, "rig/cmd/arm") == []
        # the operator's own command still gets through (the policy is not deny-all)
        assert query(operator, "rig/cmd/disarm") == [
            (True, {"command": "disarm", "accepted": True, "result": "queued"})]
        statuses = query(operator, "rig/status")
        tp.offer({"tick": 10_000, "t_ns": 0, "state": {"k": 0}})
        assert wait_for(lambda: any(m["tick"] == 10_000 for m in got["operator"]), 5)
    finally:
        fake.undeclare()
        for s in subs:
            s.undeclare()
        operator.close()
        viewer.close()
        spy.undeclare()
        tp.close()
    assert all(m["tick"] >= 0 for m in got["operator"]), "viewer's put reached the operator"
    assert all(not key.startswith("rig/state") or b"spoofed" not in data
               for key, data in inside)
    assert not any(b"SPOOFED" in data for _, data in inside)
    assert [b["lifecycle"] for _, b in statuses] == ["INACTIVE"]
    assert seen == ["disarm"]


def test_status_and_commands_are_rate_limited(port: int,
                                             caplog: pytest.LogCaptureFixture) -> None:
    """[telemetry] status_burst / commands_per_s ...: over the limit a status query is
    counted and not answered (no reply, no log line, the provider not called), a command
    query gets an error reply and a command put nothing, and the handler is not called;
    the counts are in the status.  The buckets' clock is frozen (counts, not timing)."""
    from rig.rate_limit import TokenBucket

    r = Rig(port, commands_enabled=True, status_queries_per_s=0.5, status_burst=3,
            commands_per_s=0.5, command_burst=2)
    assert (r.tp._status_limit.burst, r.tp._command_limit.burst) == (3, 2)
    assert r.tp._status_limit.rate_per_s == r.tp._command_limit.rate_per_s == 0.5
    r.tp._status_limit = TokenBucket(0.5, 3, clock=lambda: 0.0)
    r.tp._command_limit = TokenBucket(0.5, 2, clock=lambda: 0.0)
    calls: list[str] = []
    provider = r.tp._status_provider
    r.tp._status_provider = lambda: calls.append(threading.current_thread().name) or provider()
    assert r.tp.wait_connected(10), r.tp.error
    caplog.set_level(logging.DEBUG, logger="rig")
    s2 = client_session(port)
    try:
        replies: list[tuple[bool, dict[str, Any]]] = []
        # the first query that reaches the queryable is answered (the burst's first)
        assert wait_for(lambda: bool(replies.extend(query(s2, "rig/status")) or replies))
        caplog.clear()
        answers = [query(s2, "rig/status") for _ in range(20)]
        replies.extend(a for got in answers for a in got)
        # the burst of 3: 2 more answered; the 18 refused end empty, no error reply
        assert [ok for ok, _ in replies] == [True, True, True]
        assert [len(got) for got in answers] == [1, 1] + [0] * 18
        assert r.tp.status()["status_refused"] == 18
        assert not [rec for rec in caplog.records if rec.name.startswith("rig")], \
            [rec.getMessage() for rec in caplog.records]
        # built on the publisher thread, never on a Zenoh thread per query (the answers
        # above may all come from the build before the provider was wrapped: wait for
        # the next refresh, every 0.2 s)
        assert wait_for(lambda: bool(calls))
        assert set(calls) == {"rig-telemetry"}
        got = [query(s2, "rig/cmd/arm") for _ in range(5)]
        assert [g[0][0] for g in got] == [True, True, False, False, False]
        assert got[-1][0][1]["error"] == "rate limited: too many commands"
        for _ in range(5):
            s2.put("rig/cmd/arm", "{}")
        assert wait_for(lambda: r.tp._command_limit.refused >= 8)
        assert len(r.commands) == 2 and r.tp.commands_received == 2
        st = r.tp.status()
        assert st["status_refused"] == 18 and st["commands_refused"] == 8
    finally:
        s2.close()
        r.tp.close()


def test_peer_buckets_give_each_peer_its_share() -> None:
    """rig.rate_limit.PeerBuckets (clock frozen: counts, not timing): a peer that used up
    its burst is refused while another still gets its own; past MAX_PEERS the newcomers
    share one bucket, so memory stays bounded."""
    from rig.rate_limit import MAX_PEERS, OVERFLOW_PEER, PeerBuckets

    b = PeerBuckets(1.0, 2, clock=lambda: 0.0)
    assert [b.take("a") for _ in range(4)] == [True, True, False, False]
    assert [b.take("b") for _ in range(3)] == [True, True, False]
    assert b.refused == {"a": 2, "b": 1}
    for i in range(MAX_PEERS):
        b.take(f"p{i}")
    assert len(b._buckets) == MAX_PEERS + 1 and OVERFLOW_PEER in b._buckets


def test_status_queries_are_limited_per_peer(port: int) -> None:
    """A client flooding status queries on one key expression uses up its own share
    ([telemetry] status_queries_per_peer_s / status_peer_burst); a query on another key
    expression (no source id: Zenoh 1.x's default) is still answered."""
    from rig.rate_limit import PeerBuckets

    r = Rig(port, status_queries_per_peer_s=0.1, status_peer_burst=2, status_burst=1000)
    r.tp._status_peers = PeerBuckets(0.1, 2, clock=lambda: 0.0)
    assert r.tp.wait_connected(10), r.tp.error
    s2, s3 = client_session(port), client_session(port)
    try:
        assert wait_for(lambda: r.tp._status_reply is not None)
        flood = [query(s2, "rig/status") for _ in range(10)]
        assert [[ok for ok, _ in got] for got in flood] == [[True], [True]] + [[]] * 8
        other = [ok for ok, _ in query(s3, "rig/*")]
        assert other == [True]
        st = r.tp.status()
        assert st["status_refused_per_peer"] == {"key:rig/status": 8}
    finally:
        s2.close()
        s3.close()
        r.tp.close()
