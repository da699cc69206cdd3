from dataclasses import replace

import numpy as np
import torch

from qnav.training.algorithm import DoubleDQN, double_dqn_target, soft_update, td_update
from qnav.training.config import PAPER
from qnav.training.networks import QNetwork
from qnav.training.replay import Batch


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


def _terminal_batch(frame_size: int) -> Batch:
    return Batch(
        frames=np.random.default_rng(0).random((16, 6, frame_size), dtype=np.float32),
        action=np.arange(16) % 3,
        reward=np.full(16, 0.7, dtype=np.float32),
        terminal=np.ones(16, dtype=bool),
        steps=np.ones(16, dtype=np.int64),
        discount=np.full(16, 0.97, dtype=np.float32),
    )


def test_repeated_updates_fit_a_fixed_terminal_target() -> None:
    torch.manual_seed(0)
    online, target = QNetwork("recurrent", None, 32), QNetwork("recurrent", None, 32)
    optimizer = torch.optim.Adam(online.parameters(), lr=1e-3)
    batch = _terminal_batch(online.frame_size)
    first = td_update(online, target, optimizer, batch, window=5).loss
    for _ in range(150):
        last = td_update(online, target, optimizer, batch, window=5).loss
    assert last < first / 100


def test_soft_update_moves_the_target_a_fraction_towards_the_online_network() -> None:
    online, target = QNetwork("feedforward", None, 4), QNetwork("feedforward", None, 4)
    before = [p.detach().clone() for p in target.parameters()]
    soft_update(target, online, 0.25)
    for old, new, towards in zip(before, target.parameters(), online.parameters(), strict=True):
        torch.testing.assert_close(new, old + 0.25 * (towards - old))


def _same(a: QNetwork, b: QNetwork) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters(), strict=True))


def test_the_target_is_copied_every_period_and_held_between_copies() -> None:
    torch.manual_seed(0)
    settings = replace(PAPER, target_update_period=3, device="cpu", bf16_matmul=False)
    dqn = DoubleDQN(QNetwork("feedforward", None, 16), settings)
    batch = _terminal_batch(dqn.online.frame_size)
    held = [p.detach().clone() for p in dqn.target.parameters()]
    for iteration in (1, 2):
        dqn.update(batch, iteration)
        assert not _same(dqn.online, dqn.target)
        assert all(torch.equal(p, q) for p, q in zip(held, dqn.target.parameters(), strict=True))
    dqn.update(batch, 3)
    assert _same(dqn.online, dqn.target)


def test_with_smoothing_the_target_follows_every_iteration_without_copies() -> None:
    torch.manual_seed(0)
    settings = replace(PAPER, target_smoothing=0.5, target_update_period=1, device="cpu")
    dqn = DoubleDQN(QNetwork("feedforward", None, 16), settings)
    before = [p.detach().clone() for p in dqn.target.parameters()]
    dqn.update(_terminal_batch(dqn.online.frame_size), 1)
    for old, new, towards in zip(
        before, dqn.target.parameters(), dqn.online.parameters(), strict=True
    ):
        torch.testing.assert_close(new, old + 0.5 * (towards - old))
