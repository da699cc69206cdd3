"""The algorithm: double DQN (the paper's Eq. 3) with its target network and optimiser.

`DoubleDQN` holds the online network, its target copy and Adam; `update` takes one gradient
step on a sampled batch (`td_update`, the encoder run once per frame) and syncs the target:
hard copies every `target_update_period` iterations, as the paper, or Polyak averaging.
"""

from __future__ import annotations

import copy
from typing import Any, NamedTuple

import torch
from torch import Tensor
from torch.nn import functional

from qnav.training.config import TrainSettings
from qnav.training.networks import QNetwork
from qnav.training.replay import Batch


class DoubleDQN:
    """The online network, its target copy and the optimiser, on the settings' device."""

    def __init__(self, online: QNetwork, settings: TrainSettings) -> None:
        self.settings = settings
        self.device = choose_device(settings.device)
        self.bf16 = settings.bf16_matmul and (self.device.type == "cuda" or cpu_has_bf16())
        self.online = online.to(self.device)
        self.target = copy.deepcopy(self.online)
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=settings.learning_rate)

    def update(self, batch: Batch, iteration: int) -> Update:
        """One gradient step on a batch, then the target's sync; `iteration` counts the
        iterations so far, this one included."""
        settings = self.settings
        update = td_update(
            self.online,
            self.target,
            self.optimizer,
            batch,
            window=settings.window,
            grad_clip_norm=settings.grad_clip_norm,
            bf16=self.bf16,
        )
        if settings.target_smoothing:
            soft_update(self.target, self.online, settings.target_smoothing)
        elif iteration % settings.target_update_period == 0:
            self.target.load_state_dict(self.online.state_dict())
        return update

    def state_dict(self) -> dict[str, Any]:
        """The networks' and the optimiser's state, for a checkpoint."""
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, saved: dict[str, Any]) -> None:
        """Resume from a checkpoint's `state_dict`."""
        self.online.load_state_dict(saved["online"])
        self.target.load_state_dict(saved["target"])
        self.optimizer.load_state_dict(saved["optimizer"])


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


class Update(NamedTuple):
    """What one gradient step measured."""

    loss: float
    """The batch's TD loss."""


def td_update(
    online: QNetwork,
    target: QNetwork,
    optimizer: torch.optim.Optimizer,
    batch: Batch,
    *,
    window: int,
    grad_clip_norm: float = 0.0,
    bf16: bool = False,
) -> Update:
    """One gradient step on a batch; returns its TD loss and per-transition TD errors."""
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
    loss = functional.mse_loss(q_taken, y, reduction="none").mean()
    optimizer.zero_grad(set_to_none=True)
    loss.backward()  # type: ignore[no-untyped-call]
    if grad_clip_norm > 0:
        torch.nn.utils.clip_grad_norm_(
            [p for group in optimizer.param_groups for p in group["params"]], grad_clip_norm
        )
    optimizer.step()
    return Update(float(loss.item()))


def soft_update(target: QNetwork, online: QNetwork, rate: float) -> None:
    """target <- (1 - rate) * target + rate * online, parameter by parameter."""
    with torch.no_grad():
        for mine, theirs in zip(target.parameters(), online.parameters(), strict=True):
            mine.lerp_(theirs, rate)


def choose_device(name: str) -> torch.device:
    """The torch device `TrainSettings.device` names ("auto": cuda when available)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def cpu_has_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 natively (otherwise autocast would be slower)."""
    checks = ("_is_amx_tile_supported", "_is_avx512_bf16_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)
