import numpy as np
import torch

from training.learner import (
    DemonstrationLoss,
    NextScanLoss,
    double_dqn_target,
    large_margin_loss,
    td_update,
)
from training.networks import NextScanPredictor, QNetwork
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
    first = td_update(online, target, optimizer, batch, window=5).loss
    for _ in range(150):
        last = td_update(online, target, optimizer, batch, window=5).loss
    assert last < first / 100


def test_soft_update_moves_the_target_a_fraction_towards_the_online_network() -> None:
    from training.run import soft_update

    online, target = QNetwork("feedforward", None, 4), QNetwork("feedforward", None, 4)
    before = [p.detach().clone() for p in target.parameters()]
    soft_update(target, online, 0.25)
    for old, new, towards in zip(before, target.parameters(), online.parameters(), strict=True):
        torch.testing.assert_close(new, old + 0.25 * (towards - old))


def _next_scan_batch(size: int, beams: int, rng: np.random.Generator) -> Batch:
    """Windows of 6 frames in which one near return moves one beam per frame, left or right."""
    start = rng.integers(6, beams - 6, size)
    direction = rng.choice([-1, 1], size)
    scans = np.ones((size, 6, beams), dtype=np.float32)
    for t in range(6):
        scans[np.arange(size), t, start + direction * t] = 0.05
    target = np.zeros((size, 6, 3), dtype=np.float32)
    return Batch(
        frames=np.concatenate([scans, target], axis=-1),
        action=np.zeros(size, dtype=np.int64),
        reward=np.zeros(size, dtype=np.float32),
        terminal=np.ones(size, dtype=bool),
        steps=np.ones(size, dtype=np.int64),
        discount=np.full(size, 0.97, dtype=np.float32),
    )


def _next_scan_setup(beams: int) -> tuple[QNetwork, QNetwork, NextScanLoss, torch.optim.Adam]:
    torch.manual_seed(0)
    online, target = QNetwork("recurrent", beams, 32), QNetwork("recurrent", beams, 32)
    next_scan = NextScanLoss(
        predictor=NextScanPredictor(online.summary_size, beams, 64),
        weight=1.0,
        sectors=beams,
        near_fraction=0.25,
    )
    optimizer = torch.optim.Adam([*online.parameters(), *next_scan.predictor.parameters()], 3e-3)
    return online, target, next_scan, optimizer


def test_the_next_scan_loss_fits_the_next_frames_near_ranges() -> None:
    beams = 96
    online, target, next_scan, optimizer = _next_scan_setup(beams)
    batch = _next_scan_batch(64, beams, np.random.default_rng(0))
    frames = torch.from_numpy(batch.frames)

    def predicted_error() -> float:
        with torch.no_grad():
            summary = online.window_summary(online.frame_features(frames[:, :5]))
            loss = next_scan(summary, torch.from_numpy(batch.action), frames[:, 5, :beams])
        return float(loss)

    first = predicted_error()
    for _ in range(300):
        td_update(online, target, optimizer, batch, window=5, next_scan=next_scan)
    assert predicted_error() < first / 100


def test_the_next_scan_loss_trains_the_q_networks_encoder_and_lstm() -> None:
    beams = 96
    batch = _next_scan_batch(16, beams, np.random.default_rng(0))
    changed = []
    for weight in (0.0, 1.0):
        online, target, next_scan, optimizer = _next_scan_setup(beams)
        next_scan = NextScanLoss(next_scan.predictor, weight, beams, 0.25)
        td_update(online, target, optimizer, batch, window=5, next_scan=next_scan)
        changed.append([p.detach().clone() for p in online.parameters()])
    names = [name for name, _ in QNetwork("recurrent", beams, 32).named_parameters()]
    for name, without, with_loss in zip(names, *changed, strict=True):
        # The head maps the summary to Q values and is the TD loss's alone.
        assert torch.equal(without, with_loss) == name.startswith("head"), name


def test_the_large_margin_loss_vanishes_once_the_demonstrated_action_leads_by_the_margin() -> None:
    q = torch.tensor([[1.0, 0.9, 0.5], [1.0, 0.97, 0.5], [0.2, 1.0, 0.0]])
    loss = large_margin_loss(q, torch.tensor([0, 0, 0]), margin=0.05)
    # leads by 0.1: nothing; leads by 0.03: 0.02 short; trails by 0.8: 0.8 + 0.05.
    torch.testing.assert_close(loss, torch.tensor([0.0, 0.02, 0.85]))


def test_demonstrated_transitions_teach_their_action_by_the_margin() -> None:
    rng = np.random.default_rng(0)
    batch = Batch(
        frames=rng.random((8, 6, 3), dtype=np.float32),
        action=np.full(8, 2),
        reward=np.zeros(8, dtype=np.float32),
        terminal=np.ones(8, dtype=bool),
        steps=np.ones(8, dtype=np.int64),
        discount=np.full(8, 0.97, dtype=np.float32),
        demonstrated=np.ones(8, dtype=bool),
    )
    leads = []
    for demonstration in (None, DemonstrationLoss(margin=0.1, weight=1.0)):
        torch.manual_seed(0)
        online, target = QNetwork("feedforward", None, 16), QNetwork("feedforward", None, 16)
        optimizer = torch.optim.Adam(online.parameters(), lr=3e-3)
        for _ in range(200):
            td_update(online, target, optimizer, batch, window=5, demonstration=demonstration)
        with torch.no_grad():
            q = online(torch.from_numpy(batch.frames[:, :5]))
        leads.append(q[:, 2] - q[:, :2].amax(dim=1))
    # The TD loss alone fits Q(s, 2) to 0 and leaves the other actions where they fall.
    assert not (leads[0] >= 0.09).all(), leads[0]
    assert (leads[1] >= 0.09).all(), leads[1]
