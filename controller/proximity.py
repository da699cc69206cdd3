"""The proximity stop: a safety field around the car that no policy or look ahead overrides.

As safety-rated lidars do, the field depends on the direction of travel. In the car's frame
(the lidar at its centre, x ahead), with `footprint_m` the radius of the disc the car sweeps
turning in place:

- the **footprint**: the disc of radius `footprint_m`. A reading inside it is something touching
  the car: every motion is forbidden, turning in place included (a stop).
- the **travel field** of an action that drives forward: the points ahead of the centre (x > 0)
  within `footprint_m` of the segment from the centre to `travel_m` ahead, i.e. what the car's
  disc sweeps driving `travel_m` straight on. A reading inside it forbids that action; backward
  actions have the mirrored field behind.

An action that turns in place (no linear velocity) needs only the footprint clear, so the car
may still turn away from a wall it must not drive into. Readings are cleaned for the field, not
for the policy: -inf (closer than the lidar measures) and finite readings below range_min are
at 0 m (unless `lidar.below_range_min = "no_return"`, a driver that writes 0 for no echo), NaN
is ignored, +inf and readings above range_max are no return.

When the action the policy (or the look ahead) chose is forbidden, the controller takes the best
allowed one (`guarded_action`): the policy's best-valued allowed action, or with the shield's
risks the shield's rule among the allowed actions; none allowed: a stop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.lookahead import shielded_actions
from qnav.contracts.settings import check_range

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ProximitySettings:
    """The proximity stop's safety field (docs/safety.md, "The proximity stop")."""

    SECTION = "proximity"

    enabled: bool = True
    """Forbid motion into anything the lidar sees inside the field, whatever the policy chose."""
    footprint_m: float = 0.5
    """Radius the car sweeps turning in place, from the lidar (the simulator's robot radius)."""
    travel_m: float = 0.5
    """How far past the footprint the field of a driving action reaches (one robot radius)."""

    def __post_init__(self) -> None:
        check_range(self, "footprint_m", self.footprint_m, 0.0, 10.0)
        check_range(self, "travel_m", self.travel_m, 0.0, 10.0)


class Blocked(NamedTuple):
    """Which parts of the field hold a reading."""

    footprint: bool
    """Something inside the footprint: no motion at all."""
    ahead: bool
    """Something in the forward travel field."""
    behind: bool
    """Something in the backward travel field."""


CLEAR = Blocked(False, False, False)
"""A field with nothing in it."""


FOOTPRINT_TOLERANCE_M = 0.05
"""A safety field within this of the policy's robot radius fits it."""


def footprint_mismatch(footprint_m: float, robot_radius_m: float) -> str | None:
    """Why a safety field of `footprint_m` does not fit a policy trained as a robot of
    `robot_radius_m`, or None where it fits. Larger, the stop holds the car in gaps the policy
    drives through (the BARN policy, a 0.3 m robot, under the 0.5 m field: 0.449 success against
    0.855 under a 0.3 m one, docs/barn.md); smaller, the policy expects a larger car than the
    field protects."""
    if abs(footprint_m - robot_radius_m) <= FOOTPRINT_TOLERANCE_M:
        return None
    effect = (
        "the stop will hold the car in gaps the policy was trained to drive through"
        if footprint_m > robot_radius_m
        else "the policy was trained as a larger robot than the field protects"
    )
    return (
        f"proximity.footprint_m = {footprint_m:g} m, but the policy was trained as a robot of "
        f"radius {robot_radius_m:g} m: {effect}; set proximity.footprint_m to the car's own "
        "radius, and deploy a policy trained for it"
    )


def field_ranges(
    ranges_m: NDArray[np.floating],
    range_min_m: float,
    range_max_m: float,
    below_min_is_no_return: bool,
) -> F64:
    """The readings as the field reads them: -inf and finite readings below `range_min_m` at 0 m
    (below range_min ignored if the driver writes it for no echo), NaN, +inf and readings above
    `range_max_m` ignored (NaN)."""
    ranges = np.asarray(ranges_m, dtype=np.float64)
    cleaned = np.where(ranges > range_max_m, np.nan, ranges)
    below = ranges < range_min_m  # -inf and finite readings below range_min; False for NaN
    at_zero = np.nan if below_min_is_no_return else 0.0
    cleaned = np.where(below & np.isfinite(ranges), at_zero, cleaned)
    return np.where(np.isneginf(ranges), 0.0, cleaned)


def blocked_parts(angles_rad: F64, ranges_m: F64, footprint_m: float, travel_m: float) -> Blocked:
    """Which parts of the field the readings (`ranges_m` along `angles_rad` in the car's frame,
    NaN ignored) fall in; a reading on a boundary is outside."""
    seen = np.isfinite(ranges_m)
    if not seen.any():
        return CLEAR
    r, a = ranges_m[seen], angles_rad[seen]
    x, y = r * np.cos(a), r * np.sin(a)
    beyond = np.maximum(np.abs(x) - travel_m, 0.0)  # along the travel segment, past its end
    swept = np.hypot(beyond, y) < footprint_m
    return Blocked(
        footprint=bool((r < footprint_m).any()),
        ahead=bool((swept & (x > 0)).any()),
        behind=bool((swept & (x < 0)).any()),
    )


def allowed_actions(linear_mps: F64, blocked: Blocked) -> NDArray[np.bool_]:
    """(A,) whether each action (by its forward velocity) may move the car: none with the
    footprint blocked, a forward one with the forward field clear, a backward one with the
    backward field clear, a turn in place with the footprint clear."""
    linear = np.asarray(linear_mps, dtype=np.float64)
    if blocked.footprint:
        return np.zeros(linear.shape, dtype=bool)
    return ~(((linear > 0) & blocked.ahead) | ((linear < 0) & blocked.behind))


def guarded_action(
    chosen: int,
    allowed: NDArray[np.bool_],
    q_values: NDArray[np.floating],
    risks: NDArray[np.floating] | None = None,
    overrule_share: float = 0.0,
) -> int | None:
    """`chosen` if allowed; else the best allowed action: with the shield's `risks`, the
    shield's rule (`shielded_actions`) among the allowed actions, without them the best-valued
    allowed one; None (a stop) when no action is allowed."""
    if allowed[chosen]:
        return chosen
    if not allowed.any():
        return None
    q = np.where(allowed, np.asarray(q_values, dtype=np.float64), -math.inf)
    if risks is None:
        return int(np.argmax(q))
    shares = np.where(allowed, np.asarray(risks, dtype=np.float64), math.inf)
    return int(shielded_actions(q[None], shares[None], overrule_share)[0])
