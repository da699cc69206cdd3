"""`import qnav` registers the simulator's gymnasium ids, whichever of the two a program imports
first, and loads gymnasium for no process that does not load it itself."""

import subprocess
import sys
from pathlib import Path

import pytest

from qnav.gym_ids import AfterImport


def _python(code: str) -> str:
    """What `code` prints, run in a fresh interpreter outside the checkout."""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd="/", check=True
    )
    return result.stdout.strip()


@pytest.mark.parametrize(
    "imports", ["import qnav\nimport gymnasium as gym", "import gymnasium as gym\nimport qnav"]
)
def test_import_qnav_registers_the_ids_before_or_after_gymnasium(imports: str) -> None:
    made = _python(
        f"{imports}\n"
        "env = gym.make('qnav/ObstaclesInertia-v0')\n"
        "vec = gym.make_vec('qnav/WallsIncrement-v0', 2, vectorization_mode='vector_entry_point')\n"
        "print(env.unwrapped.config.name, vec.num_envs)"
    )
    assert made == "obstacles-inertia 2"


def test_the_onboard_daemons_import_qnav_without_loading_gymnasium() -> None:
    loaded = _python(
        "import sys, qnav, qnav.controller.daemon, qnav.firmware_bridge.daemon\n"
        "print('gymnasium' in sys.modules)"
    )
    assert loaded == "False"


def test_the_hook_runs_once_after_the_module_it_waits_for_has_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "waited_for.py").write_text("VALUE = 7\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    seen: list[int] = []
    hook = AfterImport("waited_for", lambda: seen.append(sys.modules["waited_for"].VALUE))
    monkeypatch.setattr(sys, "meta_path", [hook, *sys.meta_path])
    import waited_for  # type: ignore[import-not-found]

    assert waited_for.VALUE == 7
    assert seen == [7]
    assert hook not in sys.meta_path
    del sys.modules["waited_for"]
