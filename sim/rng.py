"""Counter-based random numbers: a pure function of (world seed, episode, stream, draw index).

Each world draws its episode's layout from its own seed and episode counter, never from a shared
generator, so a world gives the same episodes whether it runs alone or inside a batch of any size,
and the draw is one vectorised expression with no loop over worlds.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MUL1 = np.uint64(0xBF58476D1CE4E5B9)
_MUL2 = np.uint64(0x94D049BB133111EB)
_INV_2_53 = 1.0 / float(1 << 53)


def _splitmix64(x: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """SplitMix64's finaliser: a bijective, well-mixed 64-bit hash (it wraps on purpose)."""
    z = x + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MUL1
    z = (z ^ (z >> np.uint64(27))) * _MUL2
    return z ^ (z >> np.uint64(31))


def episode_keys(seed: NDArray[np.integer], episode: NDArray[np.integer]) -> NDArray[np.uint64]:
    """One 64-bit key per (world seed, episode index)."""
    seed_u = np.asarray(seed).astype(np.uint64)
    episode_u = np.asarray(episode).astype(np.uint64)
    return _splitmix64(_splitmix64(seed_u) ^ episode_u)


def uniform(keys: NDArray[np.uint64], stream: int, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """Uniform draws in [0, 1) of shape keys.shape + shape for a named stream of each key."""
    base = _splitmix64(keys ^ np.uint64(stream))
    count = int(np.prod(shape)) if shape else 1
    index = np.arange(count, dtype=np.uint64).reshape(shape if shape else ())
    bits = _splitmix64(base.reshape(base.shape + (1,) * len(shape)) + index * _GOLDEN)
    return (bits >> np.uint64(11)).astype(np.float64) * _INV_2_53


def uniform_at(
    keys: NDArray[np.uint64], stream: int, counter: NDArray[np.integer]
) -> NDArray[np.float64]:
    """One uniform draw in [0, 1) per key at its own counter (say, its step in the episode)."""
    bits = _splitmix64(
        _splitmix64(keys ^ np.uint64(stream)) + np.asarray(counter).astype(np.uint64) * _GOLDEN
    )
    return (bits >> np.uint64(11)).astype(np.float64) * _INV_2_53
