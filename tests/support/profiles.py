"""Configuration profiles shipped in deploy/ that tests load, and the one-layer bank as a
configuration file (for tests that run a ``rig`` command with ``--config``)."""

from __future__ import annotations

from pathlib import Path

from controller.config import LAYER_KEYS

#: deploy/thesis.toml: the thesis-literal estimation and blending profile
THESIS_PROFILE = Path(__file__).resolve().parents[2] / "deploy" / "thesis.toml"


def write_one_layer_config(directory: Path) -> Path:
    """Write ``directory``/one_layer.toml: the built-in defaults with a bank of one layer
    (every :data:`controller.config.LAYER_KEYS` = [1.0], as
    :func:`controller.config.one_layer`), and return its path."""
    path = directory / "one_layer.toml"
    path.write_text("[design]\n" + "".join(f"{key} = [1.0]\n" for key in LAYER_KEYS))
    return path
