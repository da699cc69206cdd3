"""The double-DQN update (the paper's Eq. 3), with the encoder run once per frame."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional

from training.networks import QNetwork
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
) -> float:
    """One gradient step on a batch; returns the loss."""
    device = next(online.parameters()).device
    frames = torch.from_numpy(batch.frames).to(device)
    action = torch.from_numpy(batch.action).to(device)
    steps = torch.from_numpy(batch.steps).to(device)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
        # The windows of s_t and of the bootstrap state overlap: encode each frame once.
        features = online.frame_features(frames)
        q_taken = (
            online.q_from_features(features[:, :window])
            .float()
            .gather(1, action.unsqueeze(1))
            .squeeze(1)
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
        loss = functional.smooth_l1_loss(q_taken, y)
    else:
        loss = functional.mse_loss(q_taken, y)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()  # type: ignore[no-untyped-call]
    if grad_clip_norm > 0:
        torch.nn.utils.clip_grad_norm_(online.parameters(), grad_clip_norm)
    optimizer.step()
    return float(loss.item())
