"""``rig tune`` (hil/tune.py): a tiny search runs, resumes from its journal, writes a
configuration that loads and a JSON of the documented shape."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from controller.config import default_config, load_config
from hil.tune import JOURNAL, _pareto, trial_config
from rig.cli import main

TINY = ["tune", "--plants", "1", "--duration", "1", "--roads", "iso-B", "--speed", "20",
        "--jobs", "1", "--no-progress", "--rattlespace-bound", "baseline",
        "--tire-load-bound", "baseline"]


def test_tiny_search_runs_resumes_and_writes_a_loadable_config(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "tune"
    code = main([*TINY, "--trials", "2", "--out", str(out), "--json"])
    first = json.loads(capsys.readouterr().out)
    assert code == 0
    assert [t["number"] for t in first["trials"]] == [0, 1]
    assert (out / JOURNAL).is_file()
    # resumed: the two finished trials are kept, one more is run
    assert main([*TINY, "--trials", "3", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert [t["number"] for t in res["trials"]] == [0, 1, 2]
    assert res["trials"][:2] == first["trials"]
    best, base = res["best"], res["baseline"]
    for r in (best, base):
        assert {"weights", "absorbed_power_ratio", "rattlespace_rms_ratio",
                "tire_load_rms_ratio", "faults"} <= r.keys()
        assert len(r["weights"]) == 4
    assert best["faults"] == 0 and best["feasible"]
    assert best["absorbed_power_ratio"] <= base["absorbed_power_ratio"]
    # trial 0 is the configuration's own weight set 1: the same runs as the baseline
    t0 = res["trials"][0]
    assert t0["weights"] == default_config().design.weight_sets[0]
    for k in ("absorbed_power_ratio", "rattlespace_rms_ratio", "tire_load_rms_ratio"):
        assert t0[k] == base[k]
    assert t0["constraints"] == [0.0, 0.0, 0.0, 0.0]
    # the written configuration loads; its weight set 1 is the best trial's
    cfg = load_config(out / "tuned.toml")
    assert list(cfg.weights) == best["weights"]
    assert cfg.design.weight_sets[1:] == default_config().design.weight_sets
    assert cfg.force_loop.flow_feedforward_gain == best["settings"]["flow_feedforward_gain"]
    assert (out / "pareto.png").stat().st_size > 10_000
    assert json.loads((out / "tune.json").read_text())["trials"] == res["trials"]
    # a journal of another search is refused in one line, nothing run
    assert main([*TINY, "--trials", "3", "--plants", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "another configuration or plan" in err


def test_trial_config_sets_weight_set_1_and_the_searched_settings() -> None:
    cfg = default_config()
    t = trial_config(cfg, {"rho1": 3.0, "rho2": 0.5, "rho3": 2e-9, "kp_per_n": 2e-4,
                           "flow_feedforward_gain": 0.8, "window_s": 0.05}, keep_sets=True)
    assert t.weights == (3.0, 0.5, 2e-9, 1.0) and t.design.weight_set == 1
    assert t.design.weight_sets[1:] == cfg.design.weight_sets
    assert (t.force_loop.kp_per_n, t.force_loop.flow_feedforward_gain,
            t.fuzzy.window_s) == (2e-4, 0.8, 0.05)
    assert trial_config(cfg, {"rho1": 3.0}).design.weight_sets == [[3.0, 1e2, 1e-8, 1.0]]


def test_pareto_front_against_brute_force() -> None:
    rng = np.random.default_rng(3)
    pts = rng.random((60, 3))
    pts[5] = pts[4]                                       # ties are both on the front
    front = _pareto(pts)
    for i, p in enumerate(pts):
        dominated = any(np.all(q <= p) and np.any(q < p) for q in pts)
        assert front[i] == (not dominated)


@pytest.mark.parametrize("argv", [["--rattlespace-bound", "0"], ["--tire-load-bound", "x"],
                                  ["--trials", "0"], ["--roads", "nowhere"],
                                  ["--cluster", "local:2", "--jobs", "2"]])
def test_bad_tune_arguments_are_one_line_errors(argv: list[str], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tune", "--out", str(tmp_path / "t"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "t" / JOURNAL).exists()
