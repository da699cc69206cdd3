"""The double-DQN update (the paper's Eq. 3), with the encoder run once per frame."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional

from training.networks import QNetwork
from training.replay import Batch


def double_dqn_target(
    reward: Tensor, terminal: Tensor, q_next_online: Tensor, q_next_target: Tensor, gamma: float
) -> Tensor:
    """y = r + gamma * Q_target(s', argmax_a Q_online(s', a)), and y = r where s' is terminal."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    bootstrap = q_next_target.gather(1, best).squeeze(1)
    return reward + gamma * (~terminal).to(reward.dtype) * bootstrap


def td_update(
    online: QNetwork,
    target: QNetwork,
    optimizer: torch.optim.Optimizer,
    batch: Batch,
    gamma: float,
    *,
    loss_kind: str = "mse",
    grad_clip_norm: float = 0.0,
    bf16: bool = False,
) -> float:
    """One gradient step on a batch; returns the loss."""
    device = next(online.parameters()).device
    frames = torch.from_numpy(batch.frames).to(device)
    action = torch.from_numpy(batch.action).to(device)
    window = frames.shape[1] - 1
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
        # s_t and s_t+1 share k - 1 frames: encode the k + 1 frames once for both windows.
        features = online.frame_features(frames)
        q_taken = (
            online.q_from_features(features[:, :window])
            .float()
            .gather(1, action.unsqueeze(1))
            .squeeze(1)
        )
        with torch.no_grad():
            q_next_online = online.q_from_features(features[:, 1:].detach()).float()
            q_next_target = target(frames[:, 1:]).float()
    y = double_dqn_target(
        torch.from_numpy(batch.reward).to(device),
        torch.from_numpy(batch.terminal).to(device),
        q_next_online,
        q_next_target,
        gamma,
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
