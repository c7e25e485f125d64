"""bench.loop_bench's result structure (never its timing values)."""

from __future__ import annotations

from bench import loop_bench


def test_the_sleeper_case_summarises_alongside_the_loop_cases() -> None:
    """`--cases bare,rec+tel,sleeper` crashed with KeyError 'foxglove': the sleeper's
    segment lacked the keys the summary reads."""
    summary = loop_bench._summarise([loop_bench.run_sleeper(0.01, realtime=False)])
    assert summary["ticks"] == 10
    assert summary["fox_published"] == 0 and summary["client_messages"] == 0
