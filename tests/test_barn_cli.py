"""`qnav eval --barn` and `qnav barn-convert` as a user runs them, on a folder of BARN files."""

import json
from pathlib import Path

import numpy as np

from tests.command import run_qnav
from tests.sim.test_barn import write_world


def _folder(tmp_path: Path) -> Path:
    folder = tmp_path / "worlds"
    folder.mkdir()
    # World 4: the corridor open to the goal; world 7: a wall of cylinders across it.
    write_world(folder, 4, [(-4.425, 3.0), (-0.075, 3.0)])
    write_world(folder, 7, [(-4.425 + 0.15 * i, 6.0) for i in range(30)])
    (folder / "path_files").mkdir()
    np.save(folder / "path_files" / "path_4.npy", np.array([[14, 0], [14, 29]]))
    return folder


def test_eval_barn_runs_every_world_of_a_folder_once(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    result = run_qnav("eval", "--barn", str(folder), "--agent", "goto", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [(run["world"], run["outcome"]) for run in report["runs"]] == [
        (4, "success"),
        (7, "collision"),
    ]
    assert report["success"] == 0.5 and report["runs"][0]["metric"] > 0
    text = run_qnav("eval", "--barn", str(folder), "--agent", "goto")
    assert "success    0.500" in text.stdout and "      7  collision" in text.stdout


def test_eval_barn_says_what_is_wrong_with_a_folder(tmp_path: Path) -> None:
    result = run_qnav("eval", "--barn", str(tmp_path), "--agent", "goto")
    assert result.returncode != 0 and "no world_N.world files" in result.stderr
    missing = run_qnav("eval", "--barn", str(tmp_path / "nowhere"), "--agent", "goto")
    assert missing.returncode != 0
    assert "layout.source" in missing.stderr and "BARN-format folder" in missing.stderr
    (tmp_path / "world_1.world").write_text("<sdf><world name='x'>")
    broken = run_qnav("eval", "--barn", str(tmp_path), "--agent", "goto")
    assert broken.returncode != 0 and "cannot be read" in broken.stderr


def test_barn_convert_writes_a_file_that_eval_reads(tmp_path: Path) -> None:
    out = tmp_path / "two.npz"
    converted = run_qnav(
        "barn-convert", str(_folder(tmp_path)), "-o", str(out), "--source", "here",
        "--commit", "abc", "--licence", "MIT",
    )  # fmt: skip
    assert converted.returncode == 0, converted.stderr
    again = run_qnav("eval", "--barn", str(out), "--agent", "goto", "--json")
    assert json.loads(again.stdout)["success"] == 0.5


def test_bench_sim_barn_drives_with_the_planner_too() -> None:
    result = run_qnav(
        "bench", "sim", "--barn", "--batches", "2", "--seconds", "0.05", "--no-scaling", "--json"
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["scenario"] == "barn"
    assert [r["driver"] for r in report["results"]] == ["random", "map planner"]
