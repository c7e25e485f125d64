"""Every channel schema, of a recording and of the live view, through the Foxglove apps'
own JSON Schema converter (``parseJsonSchema``, run with node).

Foxglove and Lichtblick turn a ``jsonschema`` channel's schema into field types with
``parseJsonSchema`` (Lichtblick: packages/mcap-support, src/parseJsonSchema.ts); a
channel whose schema it cannot convert is never subscribed.  Lichtblick's mcap-support
is a private workspace package (not on npm); the function as the apps ship it is in
Foxglove Studio's published ``@foxglove/studio-base`` bundle (``CONVERTER_PACKAGE``):
the same code Lichtblick forked, which throws in every case where Lichtblick's does
(Lichtblick only added ``properties ?? {}`` and the uint32 / int32 integer types).
The test installs the pinned packages with npm into a cache directory outside the
repository (kept across runs) and skips, saying so, only when npm cannot reach the
registry.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from websockets.sync.client import connect

from controller.config import default_config
from rig.recording.recorder import RunRecorder
from rig.recording.schema import TOPICS
from rig.service.loop import tick_record_layout

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests/support/parse_json_schemas.js"
#: the converter as the apps ship it (assets: webpack chunks with the module unminified)
CONVERTER_PACKAGE = "@foxglove/studio-base@1.48.0"
#: its one import
BASE64_PACKAGE = "@protobufjs/base64@1.1.2"
MODULE_MARKER = b";// CONCATENATED MODULE: ../mcap-support/src/parseJsonSchema.ts"
#: npm's messages when the registry cannot be reached
_OFFLINE = ("ENOTFOUND", "EAI_AGAIN", "ECONNREFUSED", "ETIMEDOUT", "ECONNRESET",
            "ENETUNREACH", "network")

pytestmark = pytest.mark.timeout(600)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    name = f"{CONVERTER_PACKAGE}+{BASE64_PACKAGE}".replace("/", "_").replace("@", "")
    return Path(base) / "lqg-fuzzy-rig" / "npm" / name


def _bundle(prefix: Path) -> Path | None:
    assets = prefix / "node_modules/@foxglove/studio-base/assets"
    found = sorted((p for p in assets.glob("*.js") if MODULE_MARKER in p.read_bytes()),
                   key=lambda p: p.stat().st_size) if assets.is_dir() else []
    return found[0] if found else None


@pytest.fixture(scope="module")
def converter() -> tuple[str, Path]:
    """(node, the bundle file holding parseJsonSchema), installed once into the cache."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("CONVERTER TEST NOT RUN: node / npm not installed")
    prefix = _cache_dir()
    bundle = _bundle(prefix)
    if bundle is None:
        prefix.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=prefix.name + ".", dir=prefix.parent))
        (tmp / "package.json").write_text('{"private": true}\n')
        proc = subprocess.run(
            [npm, "install", "--no-audit", "--no-fund", "--ignore-scripts",
             "--no-package-lock", "--prefix", str(tmp), CONVERTER_PACKAGE, BASE64_PACKAGE],
            capture_output=True, text=True, timeout=540, check=False)
        if proc.returncode != 0:
            shutil.rmtree(tmp, ignore_errors=True)
            text = proc.stdout + proc.stderr
            if any(s in text for s in _OFFLINE):
                pytest.skip("CONVERTER TEST NOT RUN: npm cannot reach the registry to "
                            f"install {CONVERTER_PACKAGE}: {text.strip()[-300:]}")
            pytest.fail(f"npm install {CONVERTER_PACKAGE} failed: {text[-2000:]}")
        try:
            tmp.rename(prefix)            # atomic: a parallel run may have won the race
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
        bundle = _bundle(prefix)
    assert bundle is not None, f"no parseJsonSchema module in {CONVERTER_PACKAGE} ({prefix})"
    return node, bundle


def convert(converter: tuple[str, Path], channels: list[dict[str, Any]]
            ) -> dict[str, dict[str, Any]]:
    node, bundle = converter
    proc = subprocess.run([node, str(SCRIPT), str(bundle)], input=json.dumps(channels),
                          capture_output=True, text=True, timeout=60, check=True)
    return json.loads(proc.stdout)  # type: ignore[no-any-return]


def test_the_converter_refuses_what_the_apps_refuse(converter: tuple[str, Path]) -> None:
    """The harness runs the real converter: a union type and an array without items
    fail as in the apps (issue 23), the well-known log converts."""
    bad = {"type": "object", "properties": {"fault": {"type": ["string", "null"]},
                                            "a": {"type": "array", "maxItems": 0}}}
    no_items = {"type": "object", "properties": {"a": {"type": "array", "maxItems": 0}}}
    got = convert(converter, [
        {"topic": "union", "schemaName": "x", "schema": json.dumps(bad)},
        {"topic": "no_items", "schemaName": "y", "schema": json.dumps(no_items)},
        {"topic": "log", "schemaName": "foxglove.Log", "schema": json.dumps(TOPICS["/rig/log"])},
    ])
    assert got["union"] == {"ok": False,
                            "error": 'Unsupported type ["string","null"] for fault'}
    assert not got["no_items"]["ok"] and "type" in got["no_items"]["error"]
    assert got["log"]["ok"]


def test_every_recorded_channel_converts(converter: tuple[str, Path],
                                         tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with RunRecorder(path, default_config().recording, config_toml="",
                     design_bytes=None, metadata={}, poll_s=0.001) as rec:
        rec.event(0, 0, "note", {"x": 1})
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    channels = [{"topic": c.topic, "schemaName": summary.schemas[c.schema_id].name,
                 "schema": summary.schemas[c.schema_id].data.decode()}
                for c in summary.channels.values()]
    assert {c["topic"] for c in channels} == set(TOPICS)
    got = convert(converter, channels)
    assert {t: r for t, r in got.items() if not r["ok"]} == {}
    assert set(got) == set(TOPICS)


def test_every_live_channel_converts(converter: tuple[str, Path]) -> None:
    from controller.runtime.bank import BankRuntime
    from hil.sim.closed_loop import cached_design
    from rig.foxglove_server import LIVE_TOPICS, FoxgloveView

    cfg = default_config().replace(foxglove={"enabled": True, "port": 0})
    view = FoxgloveView(cfg.foxglove, tick_record_layout(BankRuntime(cached_design(cfg),
                                                                     cfg=cfg)))
    try:
        assert view.state == "serving"
        channels: dict[str, dict[str, Any]] = {}
        with connect(f"ws://127.0.0.1:{view.port}",
                     subprotocols=["foxglove.sdk.v1"]) as ws:  # type: ignore[list-item]
            end = time.monotonic() + 20
            while set(channels) < set(LIVE_TOPICS):
                assert time.monotonic() < end, f"advertised only {sorted(channels)}"
                msg = json.loads(ws.recv(timeout=5))
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
    finally:
        view.close()
    got = convert(converter, [{"topic": t, "schemaName": c["schemaName"],
                               "schema": c["schema"]} for t, c in channels.items()])
    assert {t: r for t, r in got.items() if not r["ok"]} == {}
    assert set(got) == set(LIVE_TOPICS)
