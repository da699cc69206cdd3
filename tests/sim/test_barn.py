"""BARN's format, protocol and metric, and the committed conversion of its 300 worlds."""

from pathlib import Path

import numpy as np
import pytest

from qnav.contracts.errors import ConfigError
from qnav.sim import barn
from qnav.sim.layouts import PARKED_M, load_layouts

_CYLINDER = """<model name='{name}'>
  <static>1</static>
  <pose frame=''>{x} {y} 0 0 0 0</pose>
  <link name='link'><collision name='collision'><geometry>
    <{shape}><radius>0.075</radius><length>1</length></{shape}>
  </geometry></collision></link>
</model>"""
_GROUND = """<model name='ground_plane'><static>1</static><link name='link'>
  <collision name='collision'><geometry><plane><normal>0 0 1</normal></plane></geometry>
  </collision></link></model>"""


def write_world(
    folder: Path, number: int, centres: list[tuple[float, float]], shape: str = "cylinder"
) -> None:
    models = "".join(
        _CYLINDER.format(name=f"unit_cylinder_{i}", x=x, y=y, shape=shape)
        for i, (x, y) in enumerate(centres)
    )
    # A <state> block repeats the models with other poses: only the models' own are read.
    state = (
        "<state world_name='default'><model name='unit_cylinder_0'>"
        "<pose frame=''>9 9 0 0 0 0</pose></model></state>"
    )
    (folder / f"world_{number}.world").write_text(
        f"<sdf version='1.6'><world name='default'>{_GROUND}{models}{state}</world></sdf>"
    )


def test_a_barn_folder_is_read_with_its_paths_and_barns_start_and_goal(tmp_path: Path) -> None:
    write_world(tmp_path, 3, [(-1.0, 6.0), (-2.0, 7.5)])
    write_world(tmp_path, 11, [(-3.0, 8.0)])
    (tmp_path / "path_files").mkdir()
    np.save(tmp_path / "path_files" / "path_3.npy", np.array([[15, 0], [15, 29]]))
    layouts = barn.read_barn_folder(tmp_path)
    assert layouts.world_id.tolist() == [3, 11]
    assert layouts.cylinder_count.tolist() == [2, 1]
    np.testing.assert_allclose(layouts.cylinder_xy[0, :2], [[-1.0, 6.0], [-2.0, 7.5]])
    assert (layouts.cylinder_xy[1, 1:] == PARKED_M).all()
    assert layouts.cylinder_radius_m == 0.075
    np.testing.assert_allclose(layouts.start_pose[0], barn.START_POSE)
    np.testing.assert_allclose(layouts.goal_xy[1], [-2.25, 13.0])
    # run.py's length: start -> (0.15 * 15 - 4.575, 5.075), (.., 0.15 * 29 + 5.075) -> goal.
    a, b = np.array([-2.325, 5.075]), np.array([-2.325, 9.425])
    start, goal = np.array([-2.25, 3.0]), np.array([-2.25, 13.0])
    expected = np.linalg.norm(a - start) + np.linalg.norm(b - a) + np.linalg.norm(goal - b)
    assert layouts.path_length_m[0] == pytest.approx(expected)
    assert np.isnan(layouts.path_length_m[1])


def test_a_world_with_another_solid_is_refused_naming_the_model(tmp_path: Path) -> None:
    write_world(tmp_path, 0, [(-1.0, 6.0)], shape="box")
    with pytest.raises(ConfigError, match="unit_cylinder_0"):
        barn.read_barn_folder(tmp_path)


def test_a_folder_without_worlds_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no world_N\.world"):
        barn.read_barn_folder(tmp_path)
    with pytest.raises(ConfigError, match="not a folder"):
        barn.read_barn_folder(tmp_path / "missing")


def test_a_conversion_reads_back_to_the_millimetre(tmp_path: Path) -> None:
    write_world(tmp_path, 0, [(-1.0004, 6.0), (-2.0, 7.5)])
    write_world(tmp_path, 1, [(-3.0, 8.0)])
    layouts = barn.convert(
        tmp_path, tmp_path / "out.npz", name="two", source="here", commit="abc", licence="MIT"
    )
    loaded, provenance = load_layouts(tmp_path / "out.npz")
    assert provenance == {"source": "here", "commit": "abc", "licence": "MIT"}
    np.testing.assert_allclose(loaded.cylinder_xy, layouts.cylinder_xy, atol=5e-4)
    assert loaded.world_id.tolist() == [0, 1]
    assert loaded.name == "two"


def test_a_file_that_is_not_a_conversion_is_refused(tmp_path: Path) -> None:
    (tmp_path / "x.npz").write_bytes(b"not numpy")
    with pytest.raises(ConfigError, match="cannot be read"):
        load_layouts(tmp_path / "x.npz")


def test_the_committed_conversion_holds_barns_300_worlds() -> None:
    layouts, provenance = load_layouts(barn.BARN_FILE)
    assert layouts.world_id.tolist() == list(range(300))
    assert provenance["commit"] == "bf5a226f6088ec96bf0d2dbee3253a8ea6119b83"
    assert layouts.cylinder_radius_m == 0.075
    # Checked by reading the published files: 263 +- 51 cylinders, 181 to 365.
    counts = layouts.cylinder_count
    assert (counts.min(), counts.max()) == (181, 365)
    assert abs(counts.mean() - 263.1) < 0.1
    # Every path runs from the start through the field to the goal: at least 10 m.
    assert layouts.path_length_m.min() >= 10.0 and layouts.path_length_m.max() < 14.0


def test_the_metric_is_run_pys() -> None:
    success = np.array([True, True, True, False])
    time_s = np.array([5.0, 30.0, 200.0, 10.0])
    length = np.full(4, 10.0)
    # T = 10 m / 0.5 m/s = 20 s; t clipped to [40, 160].
    np.testing.assert_allclose(barn.metric(success, time_s, length, 0.5), [0.5, 0.5, 0.125, 0.0])
