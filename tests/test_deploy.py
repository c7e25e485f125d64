"""Deployment files: systemd units (security exposure, verify), networkd, setup script,
example configuration, Dockerfile, and why MemoryDenyWriteExecute must stay off."""

from __future__ import annotations

import ctypes.util
import json
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from fnmatch import fnmatch
from pathlib import Path

import pytest

from controller.config import config_to_dict, default_config, load_config

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
UNITS = ("rig.service", "rig-hil.service")
pytestmark = pytest.mark.timeout(120)

SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(
    SYSTEMD_ANALYZE is None,
    reason="!!! systemd-analyze missing: `apt-get install -y systemd` (Debian package "
           "'systemd') to check the unit's security exposure and syntax !!!")


def unit_entries(path: Path) -> dict[str, dict[str, list[str]]]:
    """systemd INI: sections -> key -> every value (keys may repeat), comments dropped."""
    out: dict[str, dict[str, list[str]]] = {}
    section = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out.setdefault(section, {})
            continue
        key, _, value = line.partition("=")
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


def local_copy(unit: str, tmp_path: Path) -> Path:
    """The unit with ExecStart pointing at this checkout's `rig` (verify checks it exists)."""
    rig = Path(sys.executable).parent / "rig"
    text = (DEPLOY / unit).read_text().replace("/opt/rig/.venv/bin/rig", str(rig))
    dst = tmp_path / unit
    dst.write_text(text)
    return dst


# ----------------------------------------------------------------------- systemd units


@needs_analyze
@pytest.mark.parametrize("unit", UNITS)
def test_security_exposure_at_most_2_5(unit: str) -> None:
    assert SYSTEMD_ANALYZE is not None
    res = subprocess.run([SYSTEMD_ANALYZE, "security", "--offline=true", str(DEPLOY / unit)],
                         capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", res.stdout)
    assert m, res.stdout + res.stderr
    exposure = float(m.group(1))
    print(f"\n{unit}: exposure {exposure}")
    assert exposure <= 2.5


@needs_analyze
def test_units_verify_cleanly(tmp_path: Path) -> None:
    assert SYSTEMD_ANALYZE is not None
    paths = [str(local_copy(u, tmp_path)) for u in UNITS]
    res = subprocess.run([SYSTEMD_ANALYZE, "verify", "--man=no", *paths],
                         capture_output=True, text=True, timeout=60)
    # verify returns 0 even for unknown keys; it prints them, so demand silence
    assert res.returncode == 0 and res.stdout.strip() == "" and res.stderr.strip() == "", \
        res.stdout + res.stderr


@needs_analyze
def test_verify_would_catch_a_typo(tmp_path: Path) -> None:
    """The silence asserted above is meaningful: a misspelt key is reported."""
    assert SYSTEMD_ANALYZE is not None
    p = local_copy("rig.service", tmp_path)
    p.write_text(p.read_text().replace("CPUSchedulingPolicy=fifo", "CPUSchedulingPolicy=fifoo"))
    res = subprocess.run([SYSTEMD_ANALYZE, "verify", "--man=no", str(p)],
                         capture_output=True, text=True, timeout=60)
    assert "fifoo" in res.stdout + res.stderr


def test_rig_service_contract() -> None:
    u = unit_entries(DEPLOY / "rig.service")
    svc = u["Service"]
    assert svc["Type"] == ["notify"] and svc["WatchdogSec"]
    assert svc["ExecStart"] == ["/opt/rig/.venv/bin/rig run --config /etc/rig/rig.toml"]
    assert svc["DynamicUser"] == ["yes"]
    assert svc.get("AmbientCapabilities", [""]) == [""]        # none
    assert svc.get("CapabilityBoundingSet", [""]) == [""]      # none
    assert svc["CPUSchedulingPolicy"] == ["fifo"]
    prio = int(svc["CPUSchedulingPriority"][0])
    assert 1 <= prio <= int(svc["LimitRTPRIO"][0])             # the loop may (re)claim it
    assert svc["LimitMEMLOCK"] == ["infinity"] and svc["CPUAffinity"]
    families = svc["RestrictAddressFamilies"][0].split()
    assert families == ["AF_CAN", "AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"]
    assert "@system-service" in svc["SystemCallFilter"]
    assert svc["MemoryDenyWriteExecute"] == ["no"]
    for key in ("ProtectSystem", "ProtectHome", "PrivateTmp", "NoNewPrivileges"):
        assert svc[key] in (["strict"], ["yes"]), key
    assert svc["SuccessExitStatus"] == ["130"] and svc["KillSignal"] == ["SIGINT"]
    hil = unit_entries(DEPLOY / "rig-hil.service")
    assert hil["Service"]["ExecStart"] == ["/opt/rig/.venv/bin/rig hil --config /etc/rig/rig.toml"]
    assert "vcan0" in hil["Unit"]["BindsTo"][0]


MDWE_PROBE = r'''
import ctypes
import ctypes.util
import sys

import numba  # imported (shared libraries mapped) before the filter, as at service start

class ArgCmp(ctypes.Structure):
    _fields_ = [("arg", ctypes.c_uint), ("op", ctypes.c_int),
                ("datum_a", ctypes.c_uint64), ("datum_b", ctypes.c_uint64)]

def deny_write_execute() -> None:
    """The seccomp rules of systemd's MemoryDenyWriteExecute=yes (src/shared/seccomp-util.c)."""
    lib = ctypes.CDLL(ctypes.util.find_library("seccomp") or "libseccomp.so.2", use_errno=True)
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_rule_add_array.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int,
                                           ctypes.c_uint, ctypes.POINTER(ArgCmp)]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    ALLOW, EPERM, MASKED_EQ = 0x7FFF0000, 0x00050000 | 1, 7
    PROT_WRITE, PROT_EXEC, SHM_EXEC = 2, 4, 0o100000
    ctx = lib.seccomp_init(ALLOW)
    rules = [("mmap", PROT_WRITE | PROT_EXEC), ("mprotect", PROT_EXEC),
             ("pkey_mprotect", PROT_EXEC), ("shmat", SHM_EXEC)]
    for name, mask in rules:
        nr = lib.seccomp_syscall_resolve_name(name.encode())
        cmp = ArgCmp(2, MASKED_EQ, mask, mask)
        assert lib.seccomp_rule_add_array(ctx, EPERM, nr, 1, ctypes.byref(cmp)) == 0, name
    assert lib.seccomp_load(ctx) == 0

if sys.argv[1] == "mdwe":
    deny_write_execute()
    print("filter loaded", flush=True)

@numba.njit(cache=False)
def f(x):
    return x * 2.0 + 1.0

print("jit ok", f(2.0), flush=True)
'''


@pytest.mark.skipif(not sys.platform.startswith("linux") or not ctypes.util.find_library("seccomp"),
                    reason="needs Linux seccomp and libseccomp")
def test_memory_deny_write_execute_breaks_numba_jit() -> None:
    """Why rig.service keeps MemoryDenyWriteExecute=no: under the same seccomp rules
    systemd installs for it, numba's first JIT compilation cannot make its code
    executable (the process dies), while without them it works."""
    ok = subprocess.run([sys.executable, "-c", MDWE_PROBE, "none"], capture_output=True,
                        text=True, timeout=90)
    assert ok.returncode == 0 and "jit ok 5.0" in ok.stdout, ok.stderr
    denied = subprocess.run([sys.executable, "-c", MDWE_PROBE, "mdwe"], capture_output=True,
                            text=True, timeout=90)
    assert "filter loaded" in denied.stdout, denied.stderr
    assert denied.returncode != 0 and "jit ok" not in denied.stdout


# ----------------------------------------------------------------------- networkd


NETWORKD_KEYS = {  # systemd.network(5) / systemd.netdev(5) / systemd.link(5), v252
    "80-can0.network": {"Match.Name", "Link.RequiredForOnline", "Link.ActivationPolicy",
                        "CAN.BitRate", "CAN.SamplePoint", "CAN.RestartSec",
                        "CAN.BusErrorReporting"},
    "vcan0.network": {"Match.Name", "Link.RequiredForOnline", "Link.ActivationPolicy"},
    "vcan0.netdev": {"NetDev.Name", "NetDev.Kind"},
    "80-can0.link": {"Match.OriginalName", "Link.TransmitQueueLength"},
}


@pytest.mark.parametrize("name", sorted(NETWORKD_KEYS))
def test_networkd_files(name: str) -> None:
    entries = unit_entries(DEPLOY / name)
    used = {f"{s}.{k}" for s, kv in entries.items() for k in kv}
    assert used == NETWORKD_KEYS[name]
    networkd = Path("/lib/systemd/systemd-networkd")
    if networkd.exists() and not name.endswith(".link"):
        blob = networkd.read_bytes()          # its gperf table names every Section.Key
        for key in used:
            assert b"\0" + key.encode() + b"\0" in blob, f"{key} unknown to networkd"
    if name == "80-can0.network":
        assert entries["CAN"]["BitRate"] == ["1000000"]
        assert entries["CAN"]["RestartSec"] == ["100ms"]
        assert entries["Match"]["Name"] == ["can0"]
    if name == "vcan0.netdev":
        assert entries["NetDev"] == {"Name": ["vcan0"], "Kind": ["vcan"]}


def test_setup_can_script_dry_run() -> None:
    script = DEPLOY / "setup-can.sh"
    assert subprocess.run(["bash", "-n", str(script)]).returncode == 0
    env = {"DRY_RUN": "1", "PATH": "/usr/bin:/bin"}
    out = subprocess.run(["bash", str(script), "can0"], env=env, capture_output=True,
                         text=True, check=True).stdout.splitlines()
    assert out == ["ip link set can0 down",
                   "ip link set can0 type can bitrate 1000000 restart-ms 100 berr-reporting on",
                   "ip link set can0 txqueuelen 128",
                   "ip link set can0 up"]
    out = subprocess.run(["bash", str(script), "vcan0"], env=env, capture_output=True,
                         text=True, check=True).stdout.splitlines()
    assert out[0] == "modprobe vcan" and "ip link add dev vcan0 type vcan" in out
    for bad in (["can0", "5"], ["can0", "2000000"], ["can 0"], ["can0", "1e6"]):
        res = subprocess.run(["bash", str(script), *bad], env=env, capture_output=True,
                             text=True)
        assert res.returncode == 2 and "setup-can.sh:" in res.stderr


# ----------------------------------------------------------------------- example config


def test_example_toml_is_defaults_plus_documented_overrides() -> None:
    path = DEPLOY / "rig.example.toml"
    cfg = load_config(path)
    got, want = config_to_dict(cfg), config_to_dict(default_config())
    diffs = {(s, k) for s in want for k in want[s] if got[s][k] != want[s][k]}
    assert diffs == {("can", "interface"), ("can", "channel")}
    assert cfg.can.interface == "socketcan" and cfg.can.channel == "can0"
    assert cfg.telemetry.endpoints == ["tcp/127.0.0.1:7447"]      # loopback only
    assert not cfg.telemetry.multicast_scouting and not cfg.telemetry.commands_enabled
    text = path.read_text()
    assert text.count("DEPLOY (default") == 2
    # written by deploy/make_example_toml.py: every section present
    assert set(tomllib.loads(text)) == set(want)


# ----------------------------------------------------------------------- Dockerfile


def dockerfile_instructions(path: Path) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    buf = ""
    for raw in path.read_text().splitlines():
        line = raw.rstrip()
        if not buf and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        buf += line
        op, _, args = buf.strip().partition(" ")
        out.append((op.upper(), args.strip()))
        buf = ""
    return out


def test_dockerfile_structure_and_context() -> None:
    ins = dockerfile_instructions(ROOT / "Dockerfile")
    known = {"FROM", "RUN", "COPY", "ENV", "WORKDIR", "USER", "ENTRYPOINT", "CMD", "VOLUME",
             "ARG", "LABEL", "EXPOSE"}
    assert {op for op, _ in ins} <= known
    froms = [a for op, a in ins if op == "FROM"]
    assert froms[0].startswith("python:3.11-slim") and froms[-1] == "python:3.11-slim"
    final = ins[max(i for i, (op, _) in enumerate(ins) if op == "FROM"):]
    assert ("ENTRYPOINT", '["rig"]') in final and ("CMD", '["demo"]') in final
    assert json.loads(dict(final)["ENTRYPOINT"]) == ["rig"]
    users = [a for op, a in final if op == "USER"]
    assert users and users[-1] not in ("root", "0")
    ignore = [p.strip() for p in (ROOT / ".dockerignore").read_text().splitlines()
              if p.strip() and not p.startswith("#")]
    copied: set[str] = set()
    for op, args in ins:
        if op != "COPY" or args.startswith("--from"):
            continue
        *srcs, _dst = shlex.split(args)
        for src in srcs:
            assert (ROOT / src).exists(), f"COPY {src}: missing"
            assert not any(fnmatch(src, pat) or src.startswith(pat.rstrip("/") + "/")
                           for pat in ignore), f"COPY {src} excluded by .dockerignore"
            copied.add(src)
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert pyproject["project"]["scripts"]["rig"] == "rig.cli:main"
    packages = {p.rstrip("*") for p in pyproject["tool"]["setuptools"]["packages"]["find"]
                ["include"]}
    assert packages <= copied and "pyproject.toml" in copied
    assert pyproject["project"]["readme"] in copied


def test_dockerfile_build_stage_installs_a_working_rig(tmp_path: Path) -> None:
    """No container engine runs here, so the build stage is replayed by hand: the files
    its COPY lines name (nothing else) are put in a fresh context, `pip install .` runs
    as in the image (dependencies taken from this environment instead of PyPI), and the
    installed `rig` -- not the source tree -- runs a short recorded demo from another
    directory.  Catches a package, a data file (the DBC) or a module missing from the
    image."""
    ins = dockerfile_instructions(ROOT / "Dockerfile")
    second_from = [i for i, (op, _) in enumerate(ins) if op == "FROM"][1]
    ctx = tmp_path / "ctx"
    ctx.mkdir()
    for op, args in ins[:second_from]:
        if op != "COPY":
            continue
        *srcs, _dst = shlex.split(args)
        for src in srcs:
            s = ROOT / src
            if s.is_dir():
                shutil.copytree(s, ctx / src, ignore=shutil.ignore_patterns(
                    "__pycache__", "*.pyc"))
            else:
                shutil.copy2(s, ctx / src)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    # this environment's packages (the dependencies) behind the image's own: a plain
    # path line, so the project's editable-install hook there is not run
    ours = Path(sysconfig.get_paths()["purelib"])
    site = Path(subprocess.run([venv / "bin" / "python", "-c",
                                "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    (site / "_deps_from_test_env.pth").write_text(f"{ours}\n")
    pip = subprocess.run([venv / "bin" / "python", "-m", "pip", "install", "--no-deps",
                          "--no-build-isolation", "--no-index", "--quiet",
                          "--target", str(site), "."],
                         cwd=ctx, capture_output=True, text=True, timeout=300)
    assert pip.returncode == 0, pip.stderr[-3000:]
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    env = {"PATH": f"{venv / 'bin'}:/usr/bin:/bin", "HOME": str(tmp_path),
           "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    probe = subprocess.run(
        [venv / "bin" / "python", "-c",
         "import importlib.resources as r, rig, controller, hil, rig.record_writer; "
         "print(rig.__file__); print(r.files('rig') / 'rig.dbc')"],
        cwd=run_dir, env=env, capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0, probe.stderr[-3000:]
    installed, dbc = probe.stdout.split()
    assert str(venv) in installed and str(ROOT) not in installed and Path(dbc).is_file()
    demo = subprocess.run(
        [site / "bin" / "rig", "demo", "--duration", "1", "--quiet", "--json",
         "--no-telemetry", "--no-realtime", "--record", "run.mcap"],
        cwd=run_dir, env=env, capture_output=True, text=True, timeout=600)
    assert demo.returncode == 0, demo.stderr[-3000:]
    out = json.loads(demo.stdout)
    assert out["recording_dropped"] == 0 and out["recording_error"] is None
    assert (run_dir / "run.mcap").stat().st_size > 10_000
