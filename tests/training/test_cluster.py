"""The engine-independent parts of studies and sweeps (no Ray needed): the grid, the run
names, skipping finished runs, carrying run files back, and an unreachable --address."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from qnav.cli import main
from qnav.contracts.daemon import free_port
from qnav.contracts.errors import ConfigError
from qnav.training.cluster import (
    ClusterSettings,
    RayEngine,
    changed_files,
    check_reachable,
    parse_address,
    write_files,
)
from qnav.training.study import (
    RunSpec,
    StudySettings,
    check_assignments,
    grid_points,
    parse_grid,
    pending,
    result_path,
    run_progress,
    run_study,
    sweep_plan,
    sweep_table,
    train_argv,
)


def test_a_grid_is_every_combination_with_the_last_setting_fastest() -> None:
    grid = parse_grid(["train.learning_rate=1e-4,3e-4", "train.batch_size=32, 64"])
    assert grid == (("train.learning_rate", ("1e-4", "3e-4")), ("train.batch_size", ("32", "64")))
    assert grid_points(grid) == [
        ("train.learning_rate=1e-4", "train.batch_size=32"),
        ("train.learning_rate=1e-4", "train.batch_size=64"),
        ("train.learning_rate=3e-4", "train.batch_size=32"),
        ("train.learning_rate=3e-4", "train.batch_size=64"),
    ]
    assert grid_points(()) == [()]


@pytest.mark.parametrize(
    "items",
    [["learning_rate=1e-4"], ["train.learning_rate"], ["train.lr=1,"], ["train.x=1", "train.x=2"]],
)
def test_a_malformed_grid_names_the_option(items: list[str]) -> None:
    with pytest.raises(ConfigError, match="--grid"):
        parse_grid(items)


@pytest.mark.parametrize(
    ("assignment", "named"),
    [
        ("train.lr=1e-4", "unknown setting .lr."),
        ("train.batch_size=big", "big"),
        ("lidar.beams=3", "beams"),
        ("train.seed=3", "set by --seeds"),
        ("train.threads=4", "set by --threads"),
    ],
)
def test_a_setting_no_run_could_take_is_refused_by_name_before_any_run(
    tmp_path: Path, assignment: str, named: str
) -> None:
    with pytest.raises(ConfigError, match=f"--grid {assignment}.*{named}"):
        check_assignments((assignment,), "--grid")
    specs = sweep_plan(("walls-inertia",), ("recurrent",), (0,), parse_grid([assignment]))
    with pytest.raises(ConfigError, match="--grid"):
        run_study(specs, tmp_path / "runs", results_root=tmp_path / "results")
    assert not (tmp_path / "runs").exists()
    check_assignments(("train.learning_rate=3e-4", "obstacles.count=2"), "--grid")


def test_sweep_runs_have_distinct_names_and_the_study_names_stay_as_they_were() -> None:
    specs = sweep_plan(
        ("walls-inertia",), ("recurrent",), (0, 1), parse_grid(["train.learning_rate=1e-4,3e-4"])
    )
    assert [s.name for s in specs] == [
        "walls-inertia-recurrent-seed0-learning_rate=1e-4",
        "walls-inertia-recurrent-seed1-learning_rate=1e-4",
        "walls-inertia-recurrent-seed0-learning_rate=3e-4",
        "walls-inertia-recurrent-seed1-learning_rate=3e-4",
    ]
    assert RunSpec("walls-inertia", "recurrent", 0).name == "walls-inertia-recurrent-seed0"
    odd = RunSpec("walls-inertia", "recurrent", 0, overrides=("obstacles.kind=a/b c",))
    assert "/" not in odd.name and " " not in odd.name


def test_a_run_trains_with_the_study_settings_then_its_own_world_and_learner_overrides() -> None:
    spec = RunSpec("walls-inertia", "recurrent", 3, overrides=("train.batch_size=32",))
    study = StudySettings("fast", 1, ("train.episodes=16", "obstacles.count=2"))
    argv = train_argv(spec, Path("/shared/runs/x"), study)
    assert argv[:2] == ["train", "--quiet"]
    pairs = list(zip(argv[2::2], argv[3::2], strict=True))
    assert ("--seed", "3") in pairs and ("--run-dir", "/shared/runs/x") in pairs
    assert pairs[-3:] == [
        ("--train-set", "train.episodes=16"),
        ("--set", "obstacles.count=2"),
        ("--train-set", "train.batch_size=32"),
    ]
    assert ("--train-set", "train.threads=1") in pairs


def test_finished_runs_are_skipped_and_a_study_with_none_left_starts_nothing(
    tmp_path: Path,
) -> None:
    specs = sweep_plan(("walls-inertia",), ("recurrent",), (0, 1, 2), ())
    results = tmp_path / "results"
    results.mkdir()
    result_path(results, specs[1]).write_text("{}")
    (results / f"{specs[2].name}.json.partial").write_text("{")  # half-written: not finished
    assert pending(specs, results) == [specs[0], specs[2]]
    for spec in specs:
        result_path(results, spec).write_text("{}")

    def no_engine(study: StudySettings) -> object:
        raise AssertionError("an engine was started for a study with nothing to do")

    assert run_study(specs, tmp_path / "runs", results_root=results, engine=no_engine) == []  # type: ignore[arg-type]


def test_run_progress_reads_episodes_done_of_planned_from_the_run_folder(tmp_path: Path) -> None:
    assert run_progress(tmp_path) is None
    (tmp_path / "settings.toml").write_text("[world]\nname = 'x'\n\n[train]\nepisodes = 48\n")
    (tmp_path / "progress.csv").write_text("episodes,iterations\n8,3\n16,20\n")
    assert run_progress(tmp_path) == (16, 48)


def test_sweep_table_shows_each_point_and_the_runs_not_run_yet(tmp_path: Path) -> None:
    specs = sweep_plan(
        ("walls-inertia",), ("recurrent",), (0,), parse_grid(["train.gamma=0.9,0.99"])
    )
    test = {"success": 0.5, "collision": 0.25, "unfinished": 0.25, "episodes": 8}
    result_path(tmp_path, specs[0]).write_text(json.dumps({"test": test}))
    table = sweep_table(specs, tmp_path)
    assert "| walls-inertia | recurrent | train.gamma=0.9 | 0 | 0.500 | 0.250 | 0.250 |" in table
    assert "| train.gamma=0.99 | 0 | not run yet |" in table


def test_run_files_come_back_whole_checkpoint_first_and_only_when_changed(tmp_path: Path) -> None:
    worker, driver = tmp_path / "worker", tmp_path / "driver"
    (worker / "episodes").mkdir(parents=True)
    (worker / "episodes" / "round-000000.npz").write_bytes(b"round 0")
    (worker / "episodes" / ".round-000001.partial.npz").write_bytes(b"half")
    (worker / "checkpoint.pt").write_bytes(b"state after round 0")
    (worker / "progress.csv").write_text("episodes\n8\n")
    seen: dict[str, tuple[int, int]] = {}
    sent = changed_files(worker, seen)
    assert next(iter(sent)) == "checkpoint.pt"
    assert set(sent) == {"checkpoint.pt", "episodes/round-000000.npz", "progress.csv"}
    write_files(driver, sent)
    assert changed_files(worker, seen) == {}
    (worker / "checkpoint.pt").write_bytes(b"state after round 1, longer")
    assert changed_files(worker, seen) == {"checkpoint.pt": b"state after round 1, longer"}
    assert (driver / "episodes" / "round-000000.npz").read_bytes() == b"round 0"
    assert changed_files(driver, {}) == {k: v for k, v in sent.items()}
    assert not list(driver.rglob("*.partial*"))


@pytest.mark.parametrize("path", ["../escape", "/etc/passwd", "a/../../b"])
def test_a_run_file_outside_its_folder_is_refused(tmp_path: Path, path: str) -> None:
    with pytest.raises(ValueError, match="outside"):
        write_files(tmp_path / "run", {path: b"x"})
    assert not (tmp_path / "escape").exists()


def test_addresses_parse_and_a_malformed_one_names_the_option() -> None:
    assert parse_address("10.0.0.2:6380") == ("10.0.0.2", 6380)
    assert parse_address("head") == ("head", 6379)
    assert parse_address("ray://head") == ("head", 10001)
    assert parse_address("auto") is None
    for bad in ("head:port", "head:0", ":6379", "http://x/y:1"):
        with pytest.raises(ConfigError, match="--address"):
            parse_address(bad)


def test_an_unreachable_head_is_named_after_a_bounded_wait(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    started = time.monotonic()
    with pytest.raises(ConfigError, match=f"--address {address}: no Ray head answers"):
        check_reachable(address, timeout_s=1.0)
    assert time.monotonic() - started < 30
    with pytest.raises(ConfigError, match="--local-cpus"):
        ClusterSettings(local_cpus=0)


def test_a_study_given_an_unreachable_address_says_so_and_exits_non_zero_without_runs(
    tmp_path: Path,
) -> None:
    address = f"127.0.0.1:{free_port()}"
    done = subprocess.run(
        [sys.executable, "-m", "qnav", "sweep", "--engine", "ray", "--address", address,
         "--connect-timeout-s", "2",
         "--runs-dir", str(tmp_path / "runs"), "--results-dir", str(tmp_path / "results")],
        check=False, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert f"--address {address}: no Ray head answers" in done.stderr
    assert "start  " not in done.stdout
    assert not (tmp_path / "runs").exists()


def test_ray_options_without_the_ray_engine_are_refused_by_name(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "qnav", "sweep", "--address", "head:6379",
         "--results-dir", str(tmp_path / "results")],
        check=False, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2
    assert "--address needs --engine ray" in done.stderr


def test_without_ray_the_ray_engine_says_to_install_the_cluster_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets without the extra
    specs = sweep_plan(("walls-inertia",), ("recurrent",), (0,), ())

    def ray_engine(study: StudySettings) -> RayEngine:
        return RayEngine(tmp_path / "runs", study, ClusterSettings(), main)

    with pytest.raises(ConfigError, match=r"pip install '\.\[cluster\]'"):
        run_study(specs, tmp_path / "runs", results_root=tmp_path / "results", engine=ray_engine)
    assert not (tmp_path / "runs").exists()


def test_the_study_and_the_ray_engine_module_import_without_ray() -> None:
    code = (
        "import sys\n"
        "import training.study, training.cluster, training.bench_cluster\n"
        "print('ray' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"


def test_every_new_setting_has_a_one_line_docstring() -> None:
    from qnav.contracts.settings import field_docs

    for cls in (StudySettings, ClusterSettings):
        docs = field_docs(cls)
        missing = [f for f in cls.__dataclass_fields__ if not docs.get(f)]
        assert not missing, f"{cls.__name__} fields without a docstring: {missing}"
