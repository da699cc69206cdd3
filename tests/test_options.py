"""Options generated from settings dataclasses (qnav.options), as `qnav train` uses them."""

import argparse
import dataclasses

import pytest

from qnav.cli import build_parser, main
from qnav.contracts.settings import field_docs
from qnav.options import settings_from_args
from qnav.training.config import FAST, TrainSettings


def _squeezed(text: str) -> str:
    """Text without whitespace: --help wraps lines wherever it likes."""
    return "".join(text.split())


def _train_help(capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--help"])
    return capsys.readouterr().out


def test_every_learner_setting_is_an_option_of_train_with_its_documentation(
    capsys: pytest.CaptureFixture[str],
) -> None:
    shown = _squeezed(_train_help(capsys))
    docs = field_docs(TrainSettings)
    fields = dataclasses.fields(TrainSettings)
    assert len(fields) >= 20  # the introspection sees them (29 since issue 54)
    for field in fields:
        option = "--" + field.name.replace("_", "-")
        assert option in shown, option
        assert _squeezed(docs[field.name]) in shown, field.name


def _parsed(*argv: str) -> argparse.Namespace:
    return build_parser().parse_args(["train", *argv])


def test_an_option_given_overrides_the_preset_and_one_not_given_leaves_it() -> None:
    assert settings_from_args(FAST, _parsed()) is FAST
    changed = settings_from_args(
        FAST, _parsed("--learning-rate", "3e-4", "--no-keep-best", "--model", "feedforward")
    )
    assert changed == dataclasses.replace(
        FAST, learning_rate=3e-4, keep_best=False, model="feedforward"
    )


def test_train_set_still_works_and_an_option_is_applied_over_it() -> None:
    assignments = ("--train-set", "train.gamma=0.9", "--train-set", "train.n_step=2")
    args = _parsed(*assignments, "--n-step", "3")
    changed = settings_from_args(FAST, args, assignments=args.train_assignments)
    assert (changed.gamma, changed.n_step, changed.batch_size) == (0.9, 3, FAST.batch_size)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--batch-size", "many"], "train.batch_size must be int, got 'many'"),
        (["--learning-rate", "2"], "train.learning_rate = 2.0 is out of range"),
        (["--relabel", "sometimes"], "train.relabel = 'sometimes' is not allowed"),
    ],
)
def test_a_wrong_value_exits_2_naming_the_setting(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["train", "--scenario", "walls-increment", *argv]) == 2
    assert message in capsys.readouterr().err
