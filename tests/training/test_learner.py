import numpy as np
import torch

from training.learner import double_dqn_target, td_update
from training.networks import QNetwork
from training.replay import Batch


def test_double_dqn_evaluates_the_online_argmax_with_the_target_network() -> None:
    reward = torch.tensor([0.5, 0.5])
    terminal = torch.tensor([False, False])
    online = torch.tensor([[1.0, 3.0, 2.0], [0.0, 0.0, 9.0]])
    target = torch.tensor([[10.0, 20.0, 30.0], [1.0, 2.0, 3.0]])
    y = double_dqn_target(reward, terminal, online, target, discount=0.5)
    torch.testing.assert_close(y, torch.tensor([0.5 + 0.5 * 20.0, 0.5 + 0.5 * 3.0]))


def test_terminal_transitions_do_not_bootstrap() -> None:
    y = double_dqn_target(
        torch.tensor([-1.0]), torch.tensor([True]), torch.ones(1, 3), 5 * torch.ones(1, 3), 0.97
    )
    torch.testing.assert_close(y, torch.tensor([-1.0]))


def test_repeated_updates_fit_a_fixed_terminal_target() -> None:
    torch.manual_seed(0)
    online, target = QNetwork("recurrent", None, 32), QNetwork("recurrent", None, 32)
    optimizer = torch.optim.Adam(online.parameters(), lr=1e-3)
    batch = Batch(
        frames=np.random.default_rng(0).random((16, 6, online.frame_size), dtype=np.float32),
        action=np.arange(16) % 3,
        reward=np.full(16, 0.7, dtype=np.float32),
        terminal=np.ones(16, dtype=bool),
        steps=np.ones(16, dtype=np.int64),
        discount=np.full(16, 0.97, dtype=np.float32),
    )
    first = td_update(online, target, optimizer, batch, window=5)
    for _ in range(150):
        last = td_update(online, target, optimizer, batch, window=5)
    assert last < first / 100


def test_soft_update_moves_the_target_a_fraction_towards_the_online_network() -> None:
    from training.run import soft_update

    online, target = QNetwork("feedforward", None, 4), QNetwork("feedforward", None, 4)
    before = [p.detach().clone() for p in target.parameters()]
    soft_update(target, online, 0.25)
    for old, new, towards in zip(before, target.parameters(), online.parameters(), strict=True):
        torch.testing.assert_close(new, old + 0.25 * (towards - old))
