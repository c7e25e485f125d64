"""Headless Chromium for the page-rendering tests (report, identification report)."""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

#: as the machine's probe starts it: no network of its own, no GPU, a fixed colour profile
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run", "--hide-scrollbars",
                  "--force-color-profile=srgb", "--virtual-time-budget=10000"]


def chromium() -> str:
    """The browser's path; the test is skipped (saying how to install it) without one."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("CHROMIUM NOT INSTALLED: `bash scripts/ensure-debian-packages.sh` installs "
                "the Debian package 'chromium' for the browser rendering tests")


def chromium_run(browser: str, page: Path, *args: str) -> str:
    """Run the browser on ``page`` with ``args`` (e.g. ``--dump-dom``) in a fresh profile;
    its standard output."""
    with tempfile.TemporaryDirectory(prefix="chromium-profile-") as profile:
        proc = subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                               *args, page.resolve().as_uri()],
                              capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout
