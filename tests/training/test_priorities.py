"""Prioritized replay: steps are drawn in proportion to their priority, with weights that undo
the bias, and a transition's weight scales what it teaches."""

import copy

import numpy as np
import torch

from qnav.training.algorithm import td_update
from qnav.training.networks import QNetwork
from qnav.training.replay import EpisodeReplay
from qnav.training.sampling import sample
from tests.training.test_replay import _episode, _replay


def _two_episode_replay() -> EpisodeReplay:
    return _replay(_episode(1, steps=60)[0], _episode(2, steps=60)[0])


def test_a_step_with_a_high_priority_is_drawn_in_proportion_and_weighted_down() -> None:
    replay = _two_episode_replay()
    stored = np.concatenate(replay._transitions)
    replay.reprioritise(stored, np.full(stored.size, 0.01))
    heavy = stored[3]
    replay.reprioritise(np.array([heavy]), np.array([10.0]))
    batch = sample(replay, 4000, np.random.default_rng(0), "paper", priority_exponent=1.0)
    assert batch.stored is not None and batch.weight is not None
    share = float(np.mean(batch.stored == heavy))
    expected = 10.001 / (10.001 + (stored.size - 1) * 0.011)
    assert abs(share - expected) < 0.03
    assert batch.weight.max() == 1.0
    assert batch.weight[batch.stored == heavy].max() < batch.weight[batch.stored != heavy].min()


def test_new_steps_get_the_largest_priority_seen() -> None:
    replay = _replay(_episode(1, steps=60)[0])
    replay.reprioritise(np.array([0]), np.array([7.0]))
    replay.add(_episode(2, steps=60)[0])
    newest = replay._transitions[-1]
    assert np.allclose(replay.priority[newest], 7.001)


def test_uniform_sampling_carries_no_weights() -> None:
    batch = sample(_two_episode_replay(), 64, np.random.default_rng(0), "paper")
    assert batch.weight is None and batch.stored is not None


def test_a_transition_of_weight_zero_teaches_nothing() -> None:
    torch.manual_seed(0)
    replay = _two_episode_replay()
    batch = sample(replay, 16, np.random.default_rng(1), "paper", priority_exponent=0.5)
    online = QNetwork("recurrent", 720, 16)
    before = copy.deepcopy(online.state_dict())
    optimizer = torch.optim.Adam(online.parameters(), lr=1e-2)
    zero = batch._replace(weight=np.zeros(16, dtype=np.float32))
    update = td_update(online, copy.deepcopy(online), optimizer, zero, window=5)
    assert update.loss == 0.0 and update.td_error.shape == (16,)
    for name, value in online.state_dict().items():
        torch.testing.assert_close(value, before[name])
