"""The check every refusal test makes: ``rig.cli.main`` answers with ONE line on stderr
(``rig COMMAND: ...``), the expected exit status, no traceback, nothing on stdout."""

from __future__ import annotations

import gc

import pytest

from rig.cli import main


def one_line(argv: list[str], capsys: pytest.CaptureFixture[str], *fragments: str,
             status: int = 2, stdout: bool = False) -> str:
    """Run ``rig argv``; the single stderr line (``stdout``: output there is allowed)."""
    rc = main(argv)
    gc.collect()                 # a leaked python-can bus would log a second line now
    out, err = capsys.readouterr()
    assert rc == status, (rc, err)
    assert "Traceback" not in err
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith("rig"), err
    for frag in fragments:
        assert frag in err, (frag, err)
    if not stdout:
        assert out == "", out
    return err
