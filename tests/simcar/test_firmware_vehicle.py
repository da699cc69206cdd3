"""The firmware vehicle's episode frame (the autopilot's pose, moved onto the episode's start),
and the per-period response `qnav stack --vehicle sitl` reports from the episode log.

The reading itself is tested against ArduPilot SITL (`tests/sitl/test_stack_sitl.py`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from qnav.simcar.firmware_vehicle import apply_frame, frame_change


@pytest.mark.parametrize(
    ("vehicle", "world"),
    [
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        ((12.5, -3.0, 1.2), (2.0, 3.0, -2.9)),
        ((-40.0, 7.0, -3.0), (5.0, 5.0, 3.1)),
    ],
)
def test_the_anchor_pose_reads_as_the_episode_start(
    vehicle: tuple[float, float, float], world: tuple[float, float, float]
) -> None:
    transform = frame_change(vehicle, world)
    np.testing.assert_allclose(apply_frame(transform, vehicle), world, atol=1e-9)


def test_motion_after_the_anchor_is_rigid_and_turns_with_the_frame() -> None:
    # The vehicle heads north-east (45 deg) in its frame; the episode starts heading +x.
    vehicle = (10.0, 10.0, math.pi / 4)
    transform = frame_change(vehicle, (1.0, 2.0, 0.0))
    # One metre forward along its heading, a quarter turn counter-clockwise.
    moved = (10.0 + math.sqrt(0.5), 10.0 + math.sqrt(0.5), math.pi / 4 + math.pi / 2)
    np.testing.assert_allclose(apply_frame(transform, moved), (2.0, 2.0, math.pi / 2), atol=1e-9)
    # Distances are kept: a pose 3 m to the vehicle's left stays 3 m from the anchor.
    left = (10.0 - 3 * math.sqrt(0.5), 10.0 + 3 * math.sqrt(0.5), math.pi / 4)
    np.testing.assert_allclose(apply_frame(transform, left), (1.0, 5.0, 0.0), atol=1e-9)


def test_yaw_stays_wrapped() -> None:
    transform = frame_change((0.0, 0.0, -3.0), (0.0, 0.0, 3.0))
    yaw = apply_frame(transform, (0.0, 0.0, -2.0))[2]
    assert -math.pi < yaw <= math.pi
    assert yaw == pytest.approx(4.0 - 2 * math.pi)


def test_action_response_measures_each_period_against_the_trained_step(tmp_path: Path) -> None:
    # walls-increment: forward 0.2 m or a 0.2 rad turn per 0.2 s period when trained. A car
    # that does nothing in the first period of each action and all of it afterwards.
    from qnav.stack import action_response

    poses = [[0.0, 0.0, 0.0]]
    actions = [0, 0, 0, 1, 1, -1]
    for place, action in enumerate(actions):
        x, y, yaw = poses[-1]
        first = place == 0 or actions[place - 1] != action
        if action == 0 and not first:
            x += 0.2
        elif action == 1 and not first:
            yaw += 0.2
        poses.append([x, y, yaw])
    log = tmp_path / "episodes.jsonl"
    log.write_text(json.dumps({"poses": poses, "actions": actions}) + "\n")
    response = action_response(log, "walls-increment")
    assert response["trained_m_per_step"] == response["trained_rad_per_step"] == 0.2
    assert response["forward_steps"] == 3 and response["turn_steps"] == 2
    assert response["forward_m_per_step"] == pytest.approx(0.4 / 3, abs=1e-3)
    assert response["forward_m_by_run"][:3] == [0.0, 0.2, 0.2]
    assert response["turn_rad_by_run"][:2] == [0.0, 0.2]
