"""The oracle planner fed by the onboard tracker's estimate of the state."""

from qnav.controller.perception import TrackerSettings
from qnav.lab.tracking import run_perceiving_oracle
from qnav.sim.config import SCENARIOS
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, evaluate

INERTIA = SCENARIOS["obstacles-inertia"]


def test_the_planner_on_tracks_succeeds_where_the_blind_controller_collides() -> None:
    settings = EvalSettings(episodes=48, num_worlds=48, seed=77)
    blind = evaluate(INERTIA, GoToTargetAgent(), settings)
    planned = run_perceiving_oracle(INERTIA, settings, TrackerSettings())
    assert planned.success * 48 >= blind.success * 48 + 5
