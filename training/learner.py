"""The double-DQN update (the paper's Eq. 3), with the encoder run once per frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor
from torch.nn import functional

from training.networks import NextScanPredictor, QNetwork, near_scan_bins
from training.replay import Batch


def double_dqn_target(
    reward: Tensor,
    terminal: Tensor,
    q_next_online: Tensor,
    q_next_target: Tensor,
    discount: Tensor | float,
) -> Tensor:
    """y = r + discount * Q_target(s', argmax_a Q_online(s', a)), and y = r where s' is terminal.

    With one-step transitions discount is gamma (the paper's Eq. 3); with m-step returns it is
    gamma ** m.
    """
    best = q_next_online.argmax(dim=1, keepdim=True)
    bootstrap = q_next_target.gather(1, best).squeeze(1)
    return reward + discount * (~terminal).to(reward.dtype) * bootstrap


def bootstrap_windows(features: Tensor, steps: Tensor, window: int) -> Tensor:
    """features (N, k + n, D) -> the windows (N, k, D) ending m steps after s_t."""
    index = steps[:, None] + torch.arange(window, device=features.device)[None, :]
    return features.gather(1, index[..., None].expand(-1, -1, features.shape[-1]))


@dataclass(frozen=True)
class NextScanLoss:
    """The auxiliary next-scan loss of `td_update` (`TrainSettings.next_scan_weight`)."""

    predictor: NextScanPredictor
    """The head that predicts the next frame's near ranges."""
    weight: float
    """Its squared error's weight against the TD loss."""
    sectors: int
    """Sectors of the predicted scan."""
    near_fraction: float
    """The near range as a fraction of the encoding's range."""

    def __call__(self, summary: Tensor, action: Tensor, next_scans: Tensor) -> Tensor:
        predicted = self.predictor(summary, action).float()
        wanted = near_scan_bins(next_scans, self.sectors, self.near_fraction)
        return self.weight * functional.mse_loss(predicted, wanted)


def large_margin_loss(q: Tensor, demonstrated_action: Tensor, margin: float) -> Tensor:
    """DQfD's supervised loss (Hester et al. 2018) per row: max_a [Q(s, a) + margin * (a is
    not the demonstrated action)] - Q(s, a_demo). Zero once the demonstrated action leads
    every other by the margin."""
    penalty = torch.full_like(q, margin)
    penalty.scatter_(1, demonstrated_action.unsqueeze(1), 0.0)
    taken = q.gather(1, demonstrated_action.unsqueeze(1)).squeeze(1)
    return (q + penalty).amax(dim=1) - taken


@dataclass(frozen=True)
class DemonstrationLoss:
    """The large-margin loss of `td_update` on demonstrated transitions."""

    margin: float
    """Q-value lead the demonstrated action must have over every other."""
    weight: float
    """The loss's weight against the TD loss (it is averaged over the whole batch)."""


class Update(NamedTuple):
    """What one gradient step measured."""

    loss: float
    """The batch's TD loss (importance-weighted where the batch carries weights)."""
    td_error: NDArray[np.float32]
    """(N,) y - Q(s, a) per transition, for the replay's priorities."""


def td_update(
    online: QNetwork,
    target: QNetwork,
    optimizer: torch.optim.Optimizer,
    batch: Batch,
    *,
    window: int,
    loss_kind: str = "mse",
    grad_clip_norm: float = 0.0,
    bf16: bool = False,
    next_scan: NextScanLoss | None = None,
    demonstration: DemonstrationLoss | None = None,
) -> Update:
    """One gradient step on a batch; returns its TD loss and per-transition TD errors.

    The step also follows the auxiliary next-scan loss when `next_scan` is given (its predictor
    must be in `optimizer`) and the large-margin loss on the batch's demonstrated transitions
    when `demonstration` is given."""
    device = next(online.parameters()).device
    frames = torch.from_numpy(batch.frames).to(device)
    action = torch.from_numpy(batch.action).to(device)
    steps = torch.from_numpy(batch.steps).to(device)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
        # The windows of s_t and of the bootstrap state overlap: encode each frame once.
        features = online.frame_features(frames)
        summary = online.window_summary(features[:, :window])
        q = online.head(summary).float()
        q_taken = q.gather(1, action.unsqueeze(1)).squeeze(1)
        auxiliary = (
            next_scan(summary, action, frames[:, window, : online.num_beams])
            if next_scan is not None
            else None
        )
        with torch.no_grad():
            later = bootstrap_windows(features.detach(), steps, window)
            q_next_online = online.q_from_features(later).float()
            later_target = bootstrap_windows(target.frame_features(frames), steps, window)
            q_next_target = target.q_from_features(later_target).float()
    y = double_dqn_target(
        torch.from_numpy(batch.reward).to(device),
        torch.from_numpy(batch.terminal).to(device),
        q_next_online,
        q_next_target,
        torch.from_numpy(batch.discount).to(device),
    )
    if loss_kind == "huber":
        per_transition = functional.smooth_l1_loss(q_taken, y, reduction="none")
    else:
        per_transition = functional.mse_loss(q_taken, y, reduction="none")
    if batch.weight is not None:
        per_transition = per_transition * torch.from_numpy(batch.weight).to(device)
    loss = per_transition.mean()
    total = loss if auxiliary is None else loss + auxiliary
    if demonstration is not None and batch.demonstrated is not None:
        shown = torch.from_numpy(batch.demonstrated).to(device)
        margins = large_margin_loss(q, action, demonstration.margin)
        total = total + demonstration.weight * (margins * shown).mean()
    optimizer.zero_grad(set_to_none=True)
    total.backward()  # type: ignore[no-untyped-call]
    if grad_clip_norm > 0:
        torch.nn.utils.clip_grad_norm_(
            [p for group in optimizer.param_groups for p in group["params"]], grad_clip_norm
        )
    optimizer.step()
    td_error = (y - q_taken).detach().cpu().numpy().astype(np.float32)
    return Update(float(loss.item()), td_error)
