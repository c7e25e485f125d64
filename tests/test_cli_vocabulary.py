"""One spelling per option and one vocabulary of controller modes across the
subcommands (``controller.modes`` owns the names; ``rig.argtypes`` declares the options)."""

from __future__ import annotations

import argparse

import pytest

from controller.modes import BANK_MODES, CONTROLLER_MODES, Blending, blending_of, mode_of
from rig.argtypes import bind_config
from rig.cli import build_parser

SERVICE_COMMANDS = ("run", "demo")
OFFLINE_COMMANDS = ("sim", "montecarlo")


@pytest.fixture(autouse=True)
def _default_config() -> None:
    bind_config(None)


def _parse(command: str, *argv: str) -> object:
    return build_parser(command).parse_args([command, *argv])


def _help(command: str) -> str:
    """``rig COMMAND --help`` as printed."""
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return str(sub.choices[command].format_help())


@pytest.mark.parametrize("command", SERVICE_COMMANDS + OFFLINE_COMMANDS)
def test_weights_and_controller_are_spelled_alike(command: str) -> None:
    args = _parse(command, "--weights", "2", "--controller", "lqg")
    assert args.weights == 2 and args.controller == "lqg"         # type: ignore[attr-defined]


@pytest.mark.parametrize("command", SERVICE_COMMANDS + OFFLINE_COMMANDS)
def test_old_weight_set_spelling_is_a_hidden_alias(command: str) -> None:
    args = _parse(command, "--weight-set", "2")
    assert args.weights == 2                                      # type: ignore[attr-defined]
    text = _help(command)
    assert "--weights" in text and "--weight-set" not in text


@pytest.mark.parametrize("command", SERVICE_COMMANDS)
def test_old_blending_spelling_is_a_hidden_alias(command: str) -> None:
    assert _parse(command, "--blending", "single").controller == "lqg"  # type: ignore[attr-defined]
    assert _parse(command, "--blending", "BAYES").controller == "bayes"  # type: ignore[attr-defined]
    text = _help(command)
    assert "--controller" in text and "--blending" not in text


def test_service_commands_offer_the_bank_modes_offline_ones_every_mode() -> None:
    for command in SERVICE_COMMANDS:
        for mode in BANK_MODES:
            assert _parse(command, "--controller", mode).controller == mode  # type: ignore[attr-defined]
        with pytest.raises(SystemExit):
            _parse(command, "--controller", "passive")
    for command in OFFLINE_COMMANDS:
        for mode in CONTROLLER_MODES:
            assert _parse(command, "--controller", mode).controller == mode  # type: ignore[attr-defined]


def test_mode_names_and_wire_values_round_trip() -> None:
    assert [blending_of(m) for m in BANK_MODES] == list(BANK_MODES.values())
    assert {int(b) for b in Blending} == {int(blending_of(int(b))) for b in Blending}
    for b in Blending:
        assert blending_of(mode_of(b)) is b
    with pytest.raises(ValueError, match="allowed lqg, fuzzy, bayes, moving"):
        blending_of("single")
    with pytest.raises(ValueError, match="allowed"):
        blending_of(len(Blending))


BATCH_COMMANDS = ("study", "montecarlo", "tune")


@pytest.mark.parametrize("command", BATCH_COMMANDS)
def test_batch_commands_spell_jobs_and_cluster_alike(command: str) -> None:
    assert _parse(command, "--jobs", "2").jobs == 2                # type: ignore[attr-defined]
    assert _parse(command, "--workers", "3").jobs == 3             # type: ignore[attr-defined]
    args = _parse(command, "--cluster", "local:2")
    assert args.cluster is not None and args.jobs is None          # type: ignore[attr-defined]
    text = _help(command)
    assert "--jobs" in text and "--cluster" in text and "--workers" not in text


@pytest.mark.parametrize("command", BATCH_COMMANDS)
def test_jobs_and_cluster_together_are_refused(command: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        _parse(command, "--jobs", "2", "--cluster", "local:2")
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not allowed with" in err
