"""The design artifact: everything the runtime bank needs, as plain arrays (thesis Ch. II-IV).

``design_bank(cfg)`` (:mod:`controller.design`) produces a :class:`Design`;
``save_design`` writes it as an ``.npz`` of plain arrays (no pickle) plus one JSON
metadata entry; ``load_design`` reads it back, checks :data:`ARTIFACT_VERSION`, the
field set and shapes, and, when a configuration is given, its hash.  Any mismatch
raises :class:`DesignMismatch` naming what is wrong.

Shapes (J models, S noise-table entries, W weight sets, G fuzzy grid points) are
listed in ``docs/architecture.md``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.actuator import SERVO_MODEL_SIZE
from controller.arrays import FloatArray
from controller.config import (
    MAX_COMPUTE_DELAY_TICKS,
    RigConfig,
    config_hash,
    config_to_toml,
    design_config_hash,
)

__all__ = [
    "ARTIFACT_VERSION",
    "Design",
    "DesignMismatch",
    "build_metadata",
    "design_from_bytes",
    "load_design",
    "save_design",
]

#: Bumped whenever a field is added, removed or changes meaning.
#: 3: ``servo_model`` carries the force loop's flow feedforward, ``actuator_gain`` a gain
#: on its rate-filter state (the gains are designed for the compensated actuator);
#: ``bias_gain`` (measurement-bias states of the filters) and ``bump_stop`` (the stops as
#: a known filter input) are new.
ARTIFACT_VERSION = 3


class DesignMismatch(ValueError):  # noqa: N818 (name fixed by docs/architecture.md)
    """The artifact does not fit: wrong version, wrong configuration, missing or bad field."""


@dataclass(frozen=True)
class Design:
    """The offline design of the controller bank (see docs/architecture.md for shapes)."""

    dt_s: float
    model_names: NDArray[np.str_]
    airborne: NDArray[np.bool_]
    grid_index: NDArray[np.int64]
    equilibrium: FloatArray
    Phi: FloatArray
    Gamma_u: FloatArray
    Gamma_g: FloatArray
    C_meas: FloatArray
    D_meas: FloatArray
    y_offset: FloatArray
    kalman_gain: FloatArray
    bias_gain: FloatArray
    innovation_cov: FloatArray
    innovation_cov_inv: FloatArray
    innovation_logdet: FloatArray
    filter_A: FloatArray  # noqa: N815
    filter_By: FloatArray  # noqa: N815
    filter_Bu: FloatArray  # noqa: N815
    filter_b: FloatArray
    noise_speeds_mps: FloatArray
    noise_roughness_gd: FloatArray
    lq_gain: FloatArray
    actuator_gain: FloatArray
    servo_model: FloatArray
    human_filter_Ad: FloatArray  # noqa: N815
    human_filter_Bd: FloatArray  # noqa: N815
    human_filter_Cd: FloatArray  # noqa: N815
    fuzzy_q_grid: FloatArray
    fuzzy_weight_curve: FloatArray
    static_rattlespace_m: float
    bump_stop: FloatArray
    metadata: dict[str, Any]

    @property
    def n_models(self) -> int:
        return int(self.model_names.shape[0])

    @property
    def n_noise(self) -> int:
        return int(self.kalman_gain.shape[1])

    @property
    def n_weight_sets(self) -> int:
        return int(self.lq_gain.shape[0])

    @property
    def compute_delay_ticks(self) -> int:
        """D: ticks from the sensor sample to the valve assumed by the gains."""
        return round(float(self.servo_model[4]))

    def noise_index(self, i_speed: int, i_rough: int) -> int:
        """Flat noise-table index s = i_speed * Nr + i_rough."""
        return int(i_speed) * int(self.noise_roughness_gd.shape[0]) + int(i_rough)

    def validate(self) -> None:
        """Check shapes, dtypes and finiteness; raise :class:`DesignMismatch` on any defect."""
        _validate(self)


_ARRAY_FIELDS = [f.name for f in dataclasses.fields(Design)
                 if f.name not in ("dt_s", "static_rattlespace_m", "metadata")]


def _expected_shapes(d: Design) -> dict[str, tuple[int, ...]]:
    J = d.n_models
    S = d.n_noise
    W = d.n_weight_sets
    G = int(d.fuzzy_q_grid.shape[0])
    Ns, Nr = int(d.noise_speeds_mps.shape[0]), int(d.noise_roughness_gd.shape[0])
    return {
        "model_names": (J,), "airborne": (J,), "grid_index": (J, 2), "equilibrium": (J, 4),
        "Phi": (J, 4, 4), "Gamma_u": (J, 4), "Gamma_g": (J, 4),
        "C_meas": (J, 2, 4), "D_meas": (J, 2), "y_offset": (2,),
        "kalman_gain": (J, Ns * Nr, 4, 2), "bias_gain": (J, S, 2, 2),
        "innovation_cov": (J, S, 2, 2),
        "innovation_cov_inv": (J, S, 2, 2), "innovation_logdet": (J, S),
        "filter_A": (J, S, 4, 4), "filter_By": (J, S, 4, 2), "filter_Bu": (J, S, 4),
        "filter_b": (J, S, 4), "noise_speeds_mps": (Ns,), "noise_roughness_gd": (Nr,),
        "lq_gain": (W, J, 6), "actuator_gain": (W, J, 3 + d.compute_delay_ticks),
        "servo_model": (SERVO_MODEL_SIZE,),
        "human_filter_Ad": (2, 2), "human_filter_Bd": (2,),
        "human_filter_Cd": (2,), "fuzzy_q_grid": (G,), "fuzzy_weight_curve": (G,),
        "bump_stop": (3,),
    }


def _validate(d: Design) -> None:
    sm = getattr(d, "servo_model", None)
    if not (isinstance(sm, np.ndarray) and sm.shape == (SERVO_MODEL_SIZE,)
            and np.all(np.isfinite(sm))):
        raise DesignMismatch(f"field 'servo_model' must be {SERVO_MODEL_SIZE} finite numbers")
    if not (0.0 <= sm[0] < 1.0 and sm[1] >= 0.0 and sm[2] > 0.0 and sm[3] > 0.0
            and sm[4] == round(sm[4]) and 0 <= sm[4] <= MAX_COMPUTE_DELAY_TICKS
            and sm[5] >= 0.0 and 0.0 < sm[6] <= 1.0 and sm[7] > 0.0 and 0.0 < sm[8] <= 1.0):
        raise DesignMismatch(f"field 'servo_model' out of range: {sm.tolist()}")
    for name, shape in _expected_shapes(d).items():
        arr = getattr(d, name)
        if not isinstance(arr, np.ndarray):
            raise DesignMismatch(f"field '{name}' is {type(arr).__name__}, not an array")
        if arr.shape != shape:
            raise DesignMismatch(f"field '{name}' has shape {arr.shape}, expected {shape}")
    if not (np.isfinite(d.dt_s) and d.dt_s > 0.0):
        raise DesignMismatch(f"dt_s = {d.dt_s!r} is not a positive number")
    if not np.isfinite(d.static_rattlespace_m):
        raise DesignMismatch("static_rattlespace_m is not finite")
    # NaN is allowed only in the airborne equilibrium rows and in fuzzy_weight_curve
    # (NaN there = no rule fired at that q).
    skip = {"model_names", "airborne", "grid_index", "fuzzy_weight_curve", "equilibrium"}
    for name in _ARRAY_FIELDS:
        if name in skip:
            continue
        if not np.all(np.isfinite(getattr(d, name))):
            raise DesignMismatch(f"field '{name}' has non-finite entries")
    ground = ~d.airborne
    if not np.all(np.isfinite(d.equilibrium[ground])):
        raise DesignMismatch("field 'equilibrium' has non-finite entries for on-ground models")
    if not (d.bump_stop[0] >= 0.0 and d.bump_stop[1] < d.bump_stop[2]):
        raise DesignMismatch(f"field 'bump_stop' out of range: {d.bump_stop.tolist()} "
                             "(stiffness >= 0, rebound stop below the compression stop)")
    if np.any(np.diff(d.fuzzy_q_grid) <= 0.0):
        raise DesignMismatch("field 'fuzzy_q_grid' is not strictly increasing")


def build_metadata(cfg: RigConfig) -> dict[str, Any]:
    """Artifact version, configuration hash and TOML, library versions, UTC creation time."""
    import control
    import scipy

    return {
        "artifact_version": ARTIFACT_VERSION,
        "config_hash": config_hash(cfg),
        "design_config_hash": design_config_hash(cfg),
        "config_toml": config_to_toml(cfg),
        "numpy_version": np.__version__,
        "scipy_version": scipy.__version__,
        "control_version": control.__version__,
        "created_utc": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def save_design(design: Design, path: str | Path) -> None:
    """Write ``design`` to ``path`` (``.npz``, plain arrays, metadata as a JSON string)."""
    design.validate()
    arrays: dict[str, Any] = {name: np.asarray(getattr(design, name)) for name in _ARRAY_FIELDS}
    arrays["model_names"] = np.asarray(design.model_names, dtype=np.str_)
    arrays["dt_s"] = np.asarray(float(design.dt_s))
    arrays["static_rattlespace_m"] = np.asarray(float(design.static_rattlespace_m))
    arrays["metadata"] = np.asarray(json.dumps(design.metadata, sort_keys=True))
    p = Path(path)
    with p.open("wb") as fh:  # np.savez would append ".npz" to a bare name
        np.savez(fh, **arrays)


def load_design(path: str | Path, cfg: RigConfig | None = None) -> Design:
    """Read an artifact written by :func:`save_design`.

    Raises :class:`DesignMismatch` if the version differs, a field is missing or
    malformed, or (when ``cfg`` is given) the artifact was designed for another
    configuration.  ``FileNotFoundError`` propagates.
    """
    return _read_design(Path(path), str(path), cfg)


def design_from_bytes(data: bytes, name: str = "design", cfg: RigConfig | None = None
                      ) -> Design:
    """An artifact held in memory (a recording's attachment), read as :func:`load_design`
    reads a file, without writing one; ``name`` heads its error messages."""
    return _read_design(io.BytesIO(data), name, cfg)


def _read_design(source: Path | io.BytesIO, path: str, cfg: RigConfig | None) -> Design:
    try:
        with np.load(source, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        if isinstance(exc, FileNotFoundError | IsADirectoryError | PermissionError):
            raise
        raise DesignMismatch(f"{path}: not a design artifact ({exc})") from exc
    if "metadata" not in data:
        raise DesignMismatch(f"{path}: no metadata entry")
    try:
        metadata = json.loads(str(data["metadata"]))
    except json.JSONDecodeError as exc:
        raise DesignMismatch(f"{path}: metadata is not JSON ({exc})") from exc
    version = metadata.get("artifact_version")
    if version != ARTIFACT_VERSION:
        raise DesignMismatch(f"{path}: artifact version {version!r}, this software reads "
                             f"version {ARTIFACT_VERSION}")
    missing = [n for n in [*_ARRAY_FIELDS, "dt_s", "static_rattlespace_m"] if n not in data]
    if missing:
        raise DesignMismatch(f"{path}: missing fields {missing}")
    kwargs: dict[str, Any] = {n: data[n] for n in _ARRAY_FIELDS}
    kwargs["airborne"] = data["airborne"].astype(bool)
    kwargs["grid_index"] = data["grid_index"].astype(np.int64)
    kwargs["model_names"] = data["model_names"].astype(np.str_)
    kwargs["dt_s"] = float(data["dt_s"])
    kwargs["static_rattlespace_m"] = float(data["static_rattlespace_m"])
    kwargs["metadata"] = metadata
    design = Design(**kwargs)
    design.validate()
    if cfg is not None:
        # artifacts written before design_config_hash existed: the full-config hash
        if "design_config_hash" in metadata:
            want, have = design_config_hash(cfg), metadata["design_config_hash"]
        else:
            want, have = config_hash(cfg), metadata.get("config_hash")
        if have != want:
            raise DesignMismatch(f"{path}: designed for configuration {str(have)[:12]}..., "
                                 f"the given configuration hashes to {want[:12]}... "
                                 "(re-run `rig design`)")
    return design
