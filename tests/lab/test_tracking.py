"""The onboard tracker against the simulator's truth, and the oracle planner it feeds."""

from qnav.controller.perception import TrackerSettings
from qnav.lab.tracking import TrackerCheckSettings, measure_tracker, run_perceiving_oracle
from qnav.sim.config import SCENARIOS
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, evaluate

INERTIA = SCENARIOS["obstacles-inertia"]


def test_the_tracker_reads_the_simulated_obstacles_to_centimetres() -> None:
    errors = measure_tracker(
        INERTIA, check=TrackerCheckSettings(samples=300, range_noise_m=0.02, seed=3)
    )
    assert errors.missed_share < 0.02
    for name in ("obstacle_ahead_m", "obstacle_left_m"):
        assert errors.median[name] < 0.01, errors.median
    for name in ("obstacle_forward_mps", "obstacle_leftward_mps"):
        assert errors.median[name] < 0.02, errors.median


def test_the_planner_on_tracks_succeeds_where_the_blind_controller_collides() -> None:
    settings = EvalSettings(episodes=48, num_worlds=48, seed=77)
    blind = evaluate(INERTIA, GoToTargetAgent(), settings)
    planned = run_perceiving_oracle(INERTIA, settings, TrackerSettings())
    assert planned.success * 48 >= blind.success * 48 + 5
