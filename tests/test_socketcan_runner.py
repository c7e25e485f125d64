"""tests/socketcan/run.sh's user-mode-linux path, checked on the host: the xstate fix
(tests/socketcan/uml_xstate_fix.c) against the host kernel's ptrace, and what a failed
guest boot shows and leaves behind (with a stand-in for the UML kernel)."""

from __future__ import annotations

import os
import platform
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOCKETCAN = ROOT / "tests" / "socketcan"
FIX_SOURCE = SOCKETCAN / "uml_xstate_fix.c"
# legacy FXSAVE region + XSAVE header: shorter than any host's XSAVE area with AVX
SHORT_WRITE_BYTES = 576

needs_x86_gcc = pytest.mark.skipif(
    platform.machine() != "x86_64" or shutil.which("gcc") is None,
    reason="the xstate fix is x86-64 only and is compiled with gcc")


@pytest.fixture(scope="module")
def built_fix(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(library, probe) compiled from the shipped source into this test's own directory."""
    out = tmp_path_factory.mktemp("xstate")
    lib, probe = out / "libuml_xstate_fix.so", out / "uml_xstate_probe"
    subprocess.run(["gcc", "-O2", "-Wall", "-Werror", "-shared", "-fPIC", "-o", str(lib),
                    str(FIX_SOURCE), "-ldl"], check=True, capture_output=True)
    subprocess.run(["gcc", "-O2", "-Wall", "-Werror", "-DXSTATE_PROBE", "-o", str(probe),
                    str(FIX_SOURCE)], check=True, capture_output=True)
    return lib, probe


def run_probe(probe: Path, *args: str, preload: Path | None = None
              ) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "LD_PRELOAD"}
    if preload is not None:
        env["LD_PRELOAD"] = str(preload)
    proc = subprocess.run([str(probe), *args], env=env, capture_output=True, text=True,
                          timeout=30)
    if proc.returncode == 2:
        pytest.skip(f"ptrace of a child is not permitted here: {proc.stderr.strip()}")
    return proc


@needs_x86_gcc
def test_a_short_xstate_write_is_refused_by_the_kernel_and_padded_by_the_fix(
        built_fix: tuple[Path, Path]) -> None:
    """What UML 6.1 meets on a large-XSAVE host, reproduced on any host with a write
    shorter than the host's area: the kernel refuses it (EFAULT); through the fix it
    lands, and every byte past the written ones keeps the tracee's state."""
    lib, probe = built_fix
    host_bytes = int(run_probe(probe).stdout)
    assert host_bytes > SHORT_WRITE_BYTES
    bare = run_probe(probe, "--set", str(SHORT_WRITE_BYTES))
    assert bare.returncode == 1 and "EFAULT" in bare.stdout, bare.stdout
    fixed = run_probe(probe, "--set", str(SHORT_WRITE_BYTES), preload=lib)
    assert fixed.returncode == 0 and fixed.stdout.strip().endswith("ok"), fixed.stdout


@needs_x86_gcc
@pytest.mark.parametrize("extra_bytes", [0, 64, 4096])
def test_the_fix_passes_full_size_writes_through(built_fix: tuple[Path, Path],
                                                 extra_bytes: int) -> None:
    """Harmless where it is not needed: a write of the host's size or longer (UML's own
    on a small-XSAVE host) behaves with the library exactly as without it."""
    lib, probe = built_fix
    n = str(int(run_probe(probe).stdout) + extra_bytes)
    bare, fixed = run_probe(probe, "--set", n), run_probe(probe, "--set", n, preload=lib)
    assert (bare.returncode, bare.stdout) == (fixed.returncode, fixed.stdout) == (0, bare.stdout)


def fake_tool(directory: Path, name: str, body: str) -> None:
    path = directory / name
    path.write_text("#!/bin/bash\n" + body + "\n")
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


@pytest.mark.skipif(not (ROOT / ".venv" / "bin" / "python").exists(),
                    reason="run.sh needs the project's .venv")
def test_a_guest_that_panics_at_boot_names_its_cause_and_leaves_nothing(tmp_path: Path) -> None:
    """A stand-in `linux` that fails as UML 6.1 does on an AMX host: run.sh's first line
    names the way it runs, the failure shows the kernel's own words (the ptrace error and
    the panic), the run directory is gone and nothing is written to $HOME."""
    bin_dir, modules, home, tmp = (tmp_path / d for d in ("bin", "modules", "home", "tmp"))
    for d in (bin_dir, modules / "6.1.0-fake", home, tmp):
        d.mkdir(parents=True)
    fake_tool(bin_dir, "linux", """
if [[ $1 == --version ]]; then echo 6.1.0-fake; exit 0; fi
for arg; do case $arg in uml_dir=*) mkdir -p "${arg#uml_dir=}/socketcan";; esac; done
echo "Checking that ptrace can change system call numbers...OK"
for i in $(seq 40); do echo "boot line $i"; done
echo "userspace - ptrace set fp regs failed, errno = 14"
echo "Kernel panic - not syncing: Attempted to kill init! exitcode=0x0000000b"
for i in $(seq 30); do echo " [<6000000$i>] stack line"; done
kill -ABRT $$""")
    for tool in ("modprobe", "candump", "cansend"):
        fake_tool(bin_dir, tool, "exit 0")
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "HOME": str(home),
           "TMPDIR": str(tmp), "SOCKETCAN_MODE": "uml", "SOCKETCAN_UML_KERNEL": "linux",
           "SOCKETCAN_UML_MODULES": str(modules), "SOCKETCAN_TIMEOUT_S": "60",
           "SOCKETCAN_BUILD_DIR": str(tmp_path / "build")}
    if shutil.which("ip") is None:
        fake_tool(bin_dir, "ip", "exit 0")
    proc = subprocess.run(["bash", str(SOCKETCAN / "run.sh")], env=env, capture_output=True,
                          text=True, timeout=120)
    lines = proc.stdout.splitlines()
    assert proc.returncode == 1
    assert lines[0].startswith("socketcan: runs in user-mode-linux 6.1.0-fake"), lines[0]
    assert "the guest wrote no exit code: FAILED" in proc.stdout
    cause = proc.stdout.split("The kernel's own words:", 1)[1]
    assert "ptrace set fp regs failed, errno = 14" in cause.split("UML console")[0]
    assert "Kernel panic - not syncing" in cause.split("UML console")[0]
    assert list(tmp.iterdir()) == [] and list(home.iterdir()) == []
