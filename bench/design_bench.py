"""Cost of the offline design: the whole bank, and its Riccati equations solved as
stacks against scipy's QZ solver one system at a time.

``run() -> list[dict]``: one row per item, the median wall time over repeats [s] and,
for the Riccati rows, the ratio QZ / stack.  Items: ``design_bank`` of the built-in
default (every layer) and of its one-layer bank (the configured vehicle's tire
models); the default's LQ problems (every on-ground model x weight set, actuated) by
``controller.lq.dlqr_cross_stack`` and by QZ problem by problem; the default's filter
DAREs (every model x noise entry, bias states on) by
``controller.dare.solve_filter_dares`` and by QZ.  ``python -m bench.design_bench``
prints the table (``--quick``: one repeat, QZ on every 10th system, scaled).  One BLAS
thread, as ``rig`` runs (rig.blas_threads).
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg

from controller.actuator import servo_model
from controller.config import RigConfig, default_config
from controller.dare import solve_filter_dares
from controller.design import design_bank, design_models, measurement_noise_cov
from controller.human_filter import human_filter
from controller.kalman import bias_augmented
from controller.lq import actuated_lq_problem, dlqr_cross_stack
from controller.road_noise import noise_table_entries
from rig.blas_threads import one_blas_thread

NAME = "design"
TITLE = "Offline design: the bank, and its Riccati equations as stacks vs QZ (median s)"


def _median_s(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _one_layer(cfg: RigConfig) -> RigConfig:
    return cfg.replace(design={"sprung_mass_scales": [1.0], "spring_rate_scales": [1.0],
                               "damping_scales": [1.0], "tire_stiffness_scales": [1.0]})


def _lq_stack(cfg: RigConfig) -> tuple[np.ndarray, ...]:
    hf = human_filter(cfg.design, cfg.sample_time_s)
    servo = servo_model(cfg)
    probs = [actuated_lq_problem(md.model, hf, w, servo) for md in design_models(cfg)
             if not md.model.airborne for w in cfg.design.weight_sets]
    return (np.stack([p.Ad for p in probs]), np.stack([p.Bd for p in probs]),
            np.stack([p.Qd for p in probs]), np.array([p.Rd for p in probs]),
            np.stack([p.Nd for p in probs]))


def _lq_qz(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, N: np.ndarray,
           idx: range) -> None:
    """QZ one problem at a time, balanced and rescaled as dlqr_cross did alone."""
    for i in idx:
        n = A.shape[1]
        _, (t, _) = scipy.linalg.matrix_balance(A[i], permute=False, separate=True)
        s = 1.0 / np.sqrt(R[i])
        scipy.linalg.solve_discrete_are(A[i] / t[:, None] * t[None, :],
                                        (B[i] / t).reshape(n, 1) * s,
                                        Q[i] * t[:, None] * t[None, :], np.eye(1),
                                        s=(N[i] * t).reshape(n, 1) * s)


def _filter_stack(cfg: RigConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    dt = cfg.sample_time_s
    bias_qd = np.array([cfg.design.filter_rattlespace_bias_drift ** 2,
                        cfg.design.filter_accel_bias_drift ** 2]) * dt
    systems = [bias_augmented(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * w + md.dfm.Qd_fixed,
                              bias_qd)[:3]
               for md in design_models(cfg) for _v, _gd, w in noise_table_entries(cfg.noise)]
    return (np.stack([s[0] for s in systems]), np.stack([s[1] for s in systems]),
            np.stack([s[2] for s in systems]), measurement_noise_cov(cfg))


def run(quick: bool = False) -> list[dict[str, Any]]:
    one_blas_thread()                   # as `rig design` and the batch workers run
    cfg = default_config()
    repeats = 1 if quick else 3
    every = 10 if quick else 1          # QZ on every n-th system, scaled to the stack
    rows: list[dict[str, Any]] = []
    design_bank(_one_layer(cfg))        # imports and caches warm
    for label, c in (("design_bank, default", cfg), ("design_bank, one layer",
                                                     _one_layer(cfg))):
        rows.append({"item": label, "systems": "", "median_s": _median_s(
            lambda c=c: design_bank(c), repeats), "qz_over_stack": None})
    A, B, Q, R, N = _lq_stack(cfg)
    t_stack = _median_s(lambda: dlqr_cross_stack(A, B, Q, R, N), repeats)
    t_qz = _median_s(lambda: _lq_qz(A, B, Q, R, N, range(0, A.shape[0], every)),
                     repeats) * every
    rows.append({"item": "LQ DAREs, stack", "systems": A.shape[0], "median_s": t_stack,
                 "qz_over_stack": t_qz / t_stack})
    rows.append({"item": "LQ DAREs, QZ one by one", "systems": A.shape[0],
                 "median_s": t_qz, "qz_over_stack": None})
    Phi, C, Qf, Rf = _filter_stack(cfg)
    t_stack = _median_s(lambda: solve_filter_dares(Phi, C, Qf, Rf), repeats)

    def qz() -> None:
        for i in range(0, Phi.shape[0], every):
            scipy.linalg.solve_discrete_are(Phi[i].T, C[i].T, Qf[i], Rf)
    t_qz = _median_s(qz, repeats) * every
    rows.append({"item": "filter DAREs, stack", "systems": Phi.shape[0],
                 "median_s": t_stack, "qz_over_stack": t_qz / t_stack})
    rows.append({"item": "filter DAREs, QZ one by one", "systems": Phi.shape[0],
                 "median_s": t_qz, "qz_over_stack": None})
    return rows


def notes(rows: list[dict[str, Any]]) -> list[str]:
    return ["QZ rows: scipy.linalg.solve_discrete_are per system (with --quick on every "
            "10th system, times 10); qz_over_stack = QZ time / stack time."]


if __name__ == "__main__":
    from bench.__main__ import generic_table

    out = run(quick="--quick" in sys.argv[1:])
    print(generic_table(out))
    for line in notes(out):
        print(line)
