"""Configuration profiles shipped in deploy/ that tests load."""

from __future__ import annotations

from pathlib import Path

#: deploy/thesis.toml: the thesis-literal estimation and blending profile
THESIS_PROFILE = Path(__file__).resolve().parents[2] / "deploy" / "thesis.toml"
