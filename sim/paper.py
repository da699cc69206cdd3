"""The paper's reported results (Tables I-IV and the text), the yardstick for ours.

Each entry is (success, collision, unfinished); learned agents give the mean and standard
deviation over five seeds, the random agent a single figure.
"""

from __future__ import annotations

from typing import NamedTuple


class Fractions(NamedTuple):
    """Fractions of test episodes by outcome."""

    success: float
    collision: float
    unfinished: float


TABLES: dict[str, str] = {
    "obstacles-inertia": "I",
    "walls-inertia": "II",
    "walls-increment": "III",
    "obstacles-increment": "IV",
}
"""The paper's table number of each scenario."""

RANDOM: dict[str, Fractions] = {
    "obstacles-inertia": Fractions(0.047, 0.953, 0.0),
    "walls-inertia": Fractions(0.13, 0.869, 0.001),
    "walls-increment": Fractions(0.103, 0.889, 0.008),
    "obstacles-increment": Fractions(0.064, 0.936, 0.0),
}
"""The Random Agent rows: a uniformly random action at every step."""

FEEDFORWARD: dict[str, tuple[Fractions, Fractions]] = {
    "obstacles-inertia": (Fractions(0.464, 0.462, 0.074), Fractions(0.104, 0.094, 0.019)),
    "walls-inertia": (Fractions(0.628, 0.057, 0.315), Fractions(0.222, 0.02, 0.213)),
    "walls-increment": (Fractions(0.813, 0.003, 0.184), Fractions(0.231, 0.004, 0.227)),
    "obstacles-increment": (Fractions(0.292, 0.39, 0.318), Fractions(0.204, 0.102, 0.121)),
}
"""Feedforward agent: (mean, std) over five seeds."""

RECURRENT: dict[str, tuple[Fractions, Fractions]] = {
    "obstacles-inertia": (Fractions(0.872, 0.128, 0.0), Fractions(0.034, 0.034, 0.0)),
    "walls-inertia": (Fractions(1.0, 0.0, 0.0), Fractions(0.0, 0.0, 0.0)),
    "walls-increment": (Fractions(0.995, 0.0, 0.005), Fractions(0.007, 0.0, 0.007)),
    "obstacles-increment": (Fractions(0.735, 0.257, 0.008), Fractions(0.048, 0.048, 0.013)),
}
"""Recurrent agent: (mean, std) over five seeds."""

CROSS_DYNAMICS: dict[tuple[str, str], tuple[Fractions, Fractions]] = {
    ("obstacles-increment", "obstacles-inertia"): (
        Fractions(0.765, 0.229, 0.006),
        Fractions(0.064, 0.064, 0.007),
    ),
    ("obstacles-inertia", "obstacles-increment"): (
        Fractions(0.743, 0.251, 0.006),
        Fractions(0.019, 0.021, 0.005),
    ),
}
"""Recurrent agents trained with one dynamics, tested with the other (text of section IV)."""

FEEDFORWARD_RANDOM_ACTIONS: tuple[Fractions, Fractions] = (
    Fractions(0.925, 0.069, 0.006),
    Fractions(0.096, 0.085, 0.012),
)
"""Feedforward, walls-increment, with a 10% chance of a random action at each test step."""

RECURRENT_BEST: dict[str, Fractions] = {
    "obstacles-inertia": Fractions(0.895, 0.105, 0.0),
    "walls-inertia": Fractions(1.0, 0.0, 0.0),
    "walls-increment": Fractions(1.0, 0.0, 0.0),
    "obstacles-increment": Fractions(0.78, 0.22, 0.0),
}
"""Recurrent agent: the best of the five seeds."""

FEEDFORWARD_BEST: dict[str, Fractions] = {
    "obstacles-inertia": Fractions(0.575, 0.34, 0.085),
    "walls-inertia": Fractions(0.9, 0.025, 0.075),
    "walls-increment": Fractions(0.99, 0.0, 0.01),
    "obstacles-increment": Fractions(0.54, 0.28, 0.18),
}
"""Feedforward agent: the best of the five seeds."""
