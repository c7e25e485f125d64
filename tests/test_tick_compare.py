"""bench.tick_compare's table (the turns themselves are the bench's: stood in for here):
medians and ratios of the two trees' turns, and the loop turns' faults by name with
each turn's largest lateness."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.bench_module import load_bench_module

tc = load_bench_module("tick_compare")


def _loop_turn(p50: float, faults: list[str], late_us: float
               ) -> tuple[dict[str, float], dict[str, list[str]]]:
    figures = {}
    for case in tc.LOOP_CASES:
        figures |= {f"{case} step_p50_us": p50, f"{case} step_p99_us": 2 * p50,
                    f"{case} periods_late_pct": 0.05, f"{case} faults": float(len(faults)),
                    f"{case} lateness_max_us": late_us,
                    f"{case} rig_lateness_max_us": late_us / 2}
    return figures, {"bare": [], "rec+tel": faults}


def test_loop_table_has_medians_ratios_and_the_faults_by_turn(
        monkeypatch: pytest.MonkeyPatch) -> None:
    this = iter([_loop_turn(50.0, [], 900.0), _loop_turn(60.0, ["SENSOR_STALE"], 8100.0),
                 _loop_turn(55.0, [], 700.0)])
    rev = iter([_loop_turn(40.0, [], 800.0), _loop_turn(50.0, [], 1200.0),
                _loop_turn(45.0, ["SENSOR_STALE", "OVERRUN"], 9400.0)])
    monkeypatch.setattr(tc, "export_tree", lambda rev, dest: "abcdef0123456789")
    monkeypatch.setattr(tc, "turn", lambda tree, ticks, loop_s, cpu:
                        next(this) if tree == tc.ROOT else next(rev))
    out = tc.compare("HEAD", 3, 3000, loop_s=15.0, cpu=1).splitlines()
    row = next(line for line in out if line.startswith("bare step_p50_us"))
    assert row.split()[-3:] == ["55.0", "45.0", "1.22"]
    head = "faults (lateness max of the loop / the rig [us])"
    assert f"rec+tel {head}, this tree: - (900 / 450), SENSOR_STALE (8100 / 4050), " \
           "- (700 / 350)" in out
    assert f"rec+tel {head}, abcdef0123: - (800 / 400), - (1200 / 600), " \
           "SENSOR_STALE+OVERRUN (9400 / 4700)" in out
    assert f"bare {head}, this tree: - (900 / 450), - (8100 / 4050), - (700 / 350)" in out


def test_a_turn_without_figures_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match=r"the turn in .* failed"):
        tc.turn(tmp_path, 100)                  # an empty tree: no bench to import
