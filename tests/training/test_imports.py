"""Loading a trained policy imports no training loop: the product's load path stands apart."""

import json
import subprocess
import sys
from pathlib import Path

from qnav.sim.config import scenario
from qnav.training.config import TrainSettings
from qnav.training.networks import make_network
from qnav.training.run_folder import RunFolder, RunSettings

TRAINING_LOOP = {
    "qnav.training.run",
    "qnav.training.algorithm",
    "qnav.training.collect",
    "qnav.training.replay",
    "qnav.training.sampling",
    "qnav.training.validation",
}
"""The loop and what only the loop uses."""


def _training_modules_after(code: str) -> set[str]:
    """The training modules a fresh interpreter holds after running `code`."""
    probe = code + (
        "\nimport sys\nprint(sorted(m for m in sys.modules if m.startswith('qnav.training')))"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0, done.stderr
    return set(json.loads(done.stdout.strip().splitlines()[-1].replace("'", '"')))


def test_the_loading_and_export_modules_import_no_training_loop() -> None:
    loaded = _training_modules_after("import qnav.training.run_folder, qnav.training.export")
    assert "qnav.training.run_folder" in loaded and "qnav.training.export" in loaded
    assert not loaded & TRAINING_LOOP, loaded & TRAINING_LOOP


def test_qnav_eval_of_a_run_folder_imports_no_training_loop(tmp_path: Path) -> None:
    world = scenario("walls-increment")
    settings = RunSettings(world, TrainSettings(hidden_size=8))
    folder = RunFolder(tmp_path / "run")
    folder.start(settings)
    folder.save_model(make_network(world, settings.train).state_dict(), settings)
    loaded = _training_modules_after(
        "from qnav.cli import main\n"
        f"assert main(['eval', '--policy', {str(folder.path)!r}, '--episodes', '2', '--json']) == 0"
    )
    assert "qnav.training.run_folder" in loaded  # it did load the network
    assert not loaded & TRAINING_LOOP, loaded & TRAINING_LOOP
