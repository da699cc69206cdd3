import json
from pathlib import Path

import pytest

from qnav.contracts.errors import ConfigError
from qnav.training.study import (
    MODELS,
    References,
    RunSpec,
    headroom_taken,
    parse_choices,
    parse_seeds,
    plan,
    results_markdown,
    run_study,
    skipped_lines,
)


def test_plan_covers_every_scenario_model_and_seed_once_walls_first() -> None:
    specs = plan()
    assert len(specs) == 4 * 2 * 5 == len(set(specs))
    assert specs[0].scenario.startswith("walls")
    assert specs[-1].scenario.startswith("obstacles")


def test_choices_keep_their_order_and_an_unknown_name_is_named_with_the_allowed_ones() -> None:
    assert parse_choices("--models", "feedforward,recurrent", MODELS) == MODELS[::-1]
    with pytest.raises(ConfigError, match=r"--models = 'rnn': unknown rnn; allowed: recurrent"):
        parse_choices("--models", "rnn", MODELS)
    with pytest.raises(ConfigError, match="--models = '': empty"):
        parse_choices("--models", "", MODELS)


@pytest.mark.parametrize("text", ["a", "1,,2", "-1", ""])
def test_seeds_that_are_not_non_negative_integers_name_the_option(text: str) -> None:
    with pytest.raises(ConfigError, match="--seeds"):
        parse_seeds(text)


@pytest.mark.parametrize(("jobs", "threads", "named"), [(0, None, "--jobs"), (1, 0, "--threads")])
def test_a_study_with_no_job_or_thread_names_the_option_and_starts_nothing(
    tmp_path: Path, jobs: int, threads: int | None, named: str
) -> None:
    with pytest.raises(ConfigError, match=named):
        run_study(plan(), tmp_path / "runs", results_root=tmp_path / "results", jobs=jobs,
                  threads=threads)  # fmt: skip
    assert not (tmp_path / "runs").exists()


def _result(spec: RunSpec, success: float, **extra: object) -> dict[str, object]:
    return {
        "scenario": spec.scenario, "model": spec.model, "seed": spec.seed,
        "relabel": spec.relabel,
        "test": {"success": success, "collision": 1 - success, "unfinished": 0.0, "episodes": 200},
        "iterations": 100, "collect_s": 60.0, "train_s": 120.0, "eval_s": 0.0, **extra,
    }  # fmt: skip


def test_tables_show_mean_std_best_and_the_papers_figures(tmp_path: Path) -> None:
    for seed, success in enumerate((0.9, 1.0)):
        spec = RunSpec("walls-inertia", "recurrent", seed)
        (tmp_path / f"{spec.name}.json").write_text(json.dumps(_result(spec, success)))
    ablated = RunSpec("walls-inertia", "recurrent", 0, "none")
    (tmp_path / f"{ablated.name}.json").write_text(json.dumps(_result(ablated, 0.0)))
    text = results_markdown(tmp_path, {})
    assert "| Recurrent | 2 | 0.950 +- 0.050 | 0.050 +- 0.050 | 0.000 +- 0.000 |" in text
    assert "| Recurrent (best) |  | 1.000 | 0.000 | 0.000 |  |" in text
    assert "1.0 +- 0.0 / 0.0 +- 0.0 / 0.0 +- 0.0" in text  # the paper's Table II
    assert "| Feedforward | 0 | not run yet |" in text


def test_extra_tests_are_tabulated_from_their_runs(tmp_path: Path) -> None:
    spec = RunSpec("obstacles-increment", "recurrent", 0)
    cross = {"tested_on": "obstacles-inertia", "test": _result(spec, 0.7)["test"]}
    (tmp_path / f"{spec.name}.json").write_text(
        json.dumps(_result(spec, 0.8, cross_dynamics=cross))
    )
    text = results_markdown(tmp_path, {})
    assert "trained on obstacles-increment, tested on obstacles-inertia | 1 | 0.700" in text


def test_goals_name_each_verdict_with_the_number_reached(tmp_path: Path) -> None:
    fast = {"0.99": {"episodes": 56, "iterations": 408, "wall_s": 100.0}}
    for seed, success in enumerate((1.0, 0.99)):
        spec = RunSpec("walls-increment", "recurrent", seed)
        (tmp_path / f"{spec.name}.json").write_text(
            json.dumps(_result(spec, success, first_reached=fast))
        )
    slow = RunSpec("walls-increment", "feedforward", 0)
    (tmp_path / f"{slow.name}.json").write_text(
        json.dumps(_result(slow, 0.98, train_s=700.0, first_reached={"0.99": None}))
    )
    text = results_markdown(tmp_path, {})
    assert "| Table III (walls-increment) recurrent success >= 0.995 | 0.995 | 2 | met |" in text
    assert "| Table III: recurrent beats feedforward | 0.995 vs 0.980 | 2 + 1 | met |" in text
    assert "| Table I (obstacles-inertia) recurrent success >= 0.9 | not run yet | 0 |" in text
    assert "0.99 validation success within 200 episodes | 2 of 2 runs | 2 | met |" in text
    assert (
        "| walls runs take at most 10 minutes | 2 of 3 runs (longest 12.7) | 3 | **not met** |"
        in text
    )
    assert "| walls-increment | feedforward | 1 | 12.7, 12.7 | 10 | - | 100 |" in text


def test_ablation_runs_stay_out_of_the_tables_and_fill_only_the_ablation_rows(
    tmp_path: Path,
) -> None:
    reached = {
        "0.5": {"episodes": 16, "iterations": 90, "wall_s": 60.0},
        "0.8": None,
        "0.9": {"episodes": 24, "iterations": 150, "wall_s": 90.0},
    }
    for relabel, success in (("paper", 0.5), ("none", 0.25)):
        spec = RunSpec("walls-increment", "recurrent", 0, relabel, ablation=True)
        assert spec.name.endswith(f"-ablation-{relabel}")
        (tmp_path / f"{spec.name}.json").write_text(
            json.dumps(_result(spec, success, ablation=True, first_reached=reached))
        )
    text = results_markdown(tmp_path, {})
    assert "| Recurrent | 0 | not run yet |" in text.split("## Table III")[1].split("##")[0]
    assert "| walls-increment | paper | 1 | 16 | 1.0 | - | - | 24 | 1.5 | 0.500 |" in text
    assert "| walls-increment | none | 1 | 16 | 1.0 | - | - | 24 | 1.5 | 0.250 |" in text
    assert "Status: 0 of 40" in text


def _fractions(success: float, episodes: int = 200) -> dict[str, float]:
    return {"success": success, "collision": 1 - success, "unfinished": 0.0, "episodes": episodes}


def test_obstacle_goals_ask_a_margin_over_feedforward_and_a_share_of_the_headroom(
    tmp_path: Path,
) -> None:
    gauge = {"safe": 0.6, "balanced": 0.5}
    for model, successes in (("recurrent", (0.70, 0.72)), ("feedforward", (0.65, 0.65))):
        for seed, success in enumerate(successes):
            spec = RunSpec("obstacles-inertia", model, seed)
            (tmp_path / f"{spec.name}.json").write_text(
                json.dumps(_result(spec, success, decisive=gauge))
            )
    bounds = References(_fractions(0.05, 1000), blind=_fractions(0.65), oracle=_fractions(0.93))
    text = results_markdown(tmp_path, {"obstacles-inertia": bounds})
    assert (
        "| Table I: recurrent beats feedforward by >= 0.1 | 0.710 vs 0.650 | 2 + 2 | **not met** |"
        in text
    )
    assert (
        "| Table I: recurrent takes >= 0.8 of the headroom, (success - blind) / (oracle - blind) "
        "| 0.21 (blind 0.650, oracle 0.930) | 2 | **not met** |" in text
    )
    assert "| Table III: recurrent beats feedforward | not run yet |" in text  # no margin asked
    table = text.split("## Table I:")[1].split("##")[0]
    assert "| Go-to-target (blind) | 200 episodes | 0.650 | 0.350 | 0.000 |  |" in table
    assert "| Oracle planner | 200 episodes | 0.930 |" in table
    assert "| Random | 1000 episodes | 0.050 |" in table
    assert "recurrent 0.600 / 0.500 (n = 2); feedforward 0.600 / 0.500 (n = 2)" in table


def test_headroom_is_zero_at_the_blind_controller_one_at_the_oracle_and_needs_room() -> None:
    assert headroom_taken(0.65, 0.65, 0.93) == 0.0
    assert headroom_taken(0.93, 0.65, 0.93) == 1.0
    with pytest.raises(ValueError, match="no room"):
        headroom_taken(0.9, 0.95, 0.95)


def test_each_method_beyond_the_paper_gets_its_own_row_and_goal_beside_the_papers_method(
    tmp_path: Path,
) -> None:
    spec = RunSpec("obstacles-inertia", "recurrent", 0)
    (tmp_path / f"{spec.name}.json").write_text(json.dumps(_result(spec, 0.66)))
    (tmp_path / "shielded").mkdir()
    for seed, success in enumerate((0.87, 0.89, 0.88)):
        path = tmp_path / "shielded" / f"obstacles-inertia-recurrent-seed{seed}.json"
        path.write_text(json.dumps(_fractions(success, 1000)))
    for seed, success in enumerate((0.84, 0.86)):  # the feedforward runs, shielded
        path = tmp_path / "shielded" / f"obstacles-inertia-feedforward-seed{seed}.json"
        path.write_text(json.dumps(_fractions(success, 1000)))
    bounds = References(_fractions(0.05, 1000), blind=_fractions(0.65), oracle=_fractions(0.95))
    text = results_markdown(tmp_path, {"obstacles-inertia": bounds})
    table = text.split("## Table I:")[1].split("##")[0]
    assert "| Recurrent, shielded (beyond the paper; 1000 episodes) | 3 | 0.880 +- 0.008 |" in table
    assert (
        "| Feedforward, shielded (beyond the paper; 1000 episodes) | 2 | 0.850 +- 0.010 |" in table
    )
    assert "| Recurrent | 1 | 0.660 +- 0.000 |" in table  # the paper's method keeps its rows
    assert "Shielded: each run's DQN" in table
    assert (
        "| Table I, beyond the paper: recurrent shielded reaches the paper's 0.872 and >= 0.8 of "
        "the headroom | 0.880, headroom 0.77 | 3 | **not met** |" in text
    )
    assert (
        "| Table I, beyond the paper: recurrent shielded beats feedforward shielded by >= 0.1 | "
        "0.880 vs 0.850 | 3 + 2 | **not met** |" in text
    )
    assert "beyond the paper" not in text.split("## Table IV:")[1]  # none there
    for path in (tmp_path / "shielded").glob("*-feedforward-*.json"):
        path.unlink()
    alone = results_markdown(tmp_path, {"obstacles-inertia": bounds})
    assert "recurrent shielded beats" not in alone  # nothing to compare with


def _fresh_clone(tmp_path: Path) -> tuple[Path, Path, RunSpec]:
    """A results folder as committed (one run and one shielded result) and no run folders."""
    results = tmp_path / "results"
    (results / "shielded").mkdir(parents=True)
    spec = RunSpec("walls-inertia", "recurrent", 0)
    (results / f"{spec.name}.json").write_text(json.dumps(_result(spec, 1.0)))
    (results / "shielded" / f"{spec.name}.json").write_text(json.dumps(_result(spec, 1.0)["test"]))
    return results, tmp_path / "runs", spec


def test_a_study_without_networks_says_what_it_skips_and_how_to_train_again(
    tmp_path: Path,
) -> None:
    results, runs, spec = _fresh_clone(tmp_path)
    other = RunSpec("walls-inertia", "feedforward", 0)
    text = "\n".join(skipped_lines([spec, other], runs, results, trained=False))
    assert f"skipping 1 of 2 runs: each has its result in {results}/" in text
    assert f"none of their networks is in {runs}/" in text
    assert f"delete its {results}/NAME.json" in text
    assert "skipping 1 runs without a result (--tables-only)" in text
    assert f"not re-evaluating the 1 shielded results in {results / 'shielded'}/" in text
    assert "qnav eval --policy RUN --lookahead shield" in text
    (runs / spec.name).mkdir(parents=True)
    (runs / spec.name / "model.pt").write_bytes(b"")
    assert "none of their networks" not in "\n".join(skipped_lines([spec], runs, results))


def test_reproduce_in_a_fresh_clone_names_what_it_skipped_before_writing_the_tables(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from qnav.cli import main

    results, runs, _ = _fresh_clone(tmp_path)
    random = {"success": 0.1, "collision": 0.9, "unfinished": 0.0, "episodes": 1000}
    monkeypatch.setattr("qnav.verbs.learn._references", lambda world: References(random))
    docs = tmp_path / "results.md"
    argv = ["reproduce", "--scenarios", "walls-inertia", "--models", "recurrent", "--seeds", "0"]
    argv += ["--results-dir", str(results), "--runs-dir", str(runs), "--docs", str(docs)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "skipping 1 of 1 runs" in out
    assert "none of their networks" in out
    assert "not re-evaluating the 1 shielded results" in out
    assert docs.exists() and not runs.exists()
