"""The paper's Q-networks, recurrent and feedforward, with or without the lidar encoder.

Input: a window of encoded frames (N, k, F) from `contracts.observation.encode_frame`, each
frame the scaled scan (B values, absent for the toy car) followed by the scaled target features
(3 values). Output: Q values (N, 3).
"""

from __future__ import annotations

from typing import Literal, cast

import torch
from torch import Tensor, nn

from contracts.actions import NUM_ACTIONS
from contracts.observation import TARGET_FEATURES
from contracts.policy_file import CONV_CHANNELS, CONV_KERNEL, CONV_LAYERS, CONV_STRIDE

ModelKind = Literal["recurrent", "feedforward"]


def conv_output_length(num_beams: int) -> int:
    """Length of the lidar encoder's output per channel."""
    length = num_beams
    for _ in range(CONV_LAYERS):
        length = (length - CONV_KERNEL) // CONV_STRIDE + 1
    return length


class LidarEncoder(nn.Module):
    """3 x Conv1d(8 channels, kernel 6, stride 3) + ReLU over a scan: (M, B) -> (M, 8 * L)."""

    def __init__(self, num_beams: int) -> None:
        super().__init__()
        if conv_output_length(num_beams) < 1:
            raise ValueError(f"num_beams = {num_beams} is too few for three stride-3 convolutions")
        layers: list[nn.Module] = []
        channels = 1
        for _ in range(CONV_LAYERS):
            layers += [nn.Conv1d(channels, CONV_CHANNELS, CONV_KERNEL, CONV_STRIDE), nn.ReLU()]
            channels = CONV_CHANNELS
        self.layers = nn.Sequential(*layers)
        self.output_size = CONV_CHANNELS * conv_output_length(num_beams)

    def forward(self, scans: Tensor) -> Tensor:
        return self.layers(scans.unsqueeze(1)).flatten(1)  # type: ignore[no-any-return]


class QNetwork(nn.Module):
    """Frames -> per-frame features -> LSTM over the window (or the last frame alone) -> Q.

    recurrent:   features -> LSTM(hidden) -> Linear(hidden) + ReLU -> Linear(3)
    feedforward: features of the last frame -> Linear(hidden) + ReLU -> Linear(3)
    The LSTM starts from a zero state on every window, as in the paper.
    """

    def __init__(self, kind: ModelKind, num_beams: int | None, hidden_size: int = 512) -> None:
        super().__init__()
        self.kind: ModelKind = kind
        self.num_beams = num_beams or 0
        self.hidden_size = hidden_size
        self.encoder = LidarEncoder(num_beams) if num_beams else None
        feature_size = (self.encoder.output_size if self.encoder else 0) + TARGET_FEATURES
        self.lstm = (
            nn.LSTM(feature_size, hidden_size, batch_first=True) if kind == "recurrent" else None
        )
        head_input = hidden_size if kind == "recurrent" else feature_size
        self.head = nn.Sequential(
            nn.Linear(head_input, hidden_size), nn.ReLU(), nn.Linear(hidden_size, NUM_ACTIONS)
        )

    @property
    def frame_size(self) -> int:
        """Values per input frame."""
        return self.num_beams + TARGET_FEATURES

    def frame_features(self, frames: Tensor) -> Tensor:
        """(N, T, F) frames -> (N, T, D) features; the encoder runs once per frame."""
        if self.encoder is None:
            return frames
        n, t, _ = frames.shape
        scans = frames[..., : self.num_beams].reshape(n * t, self.num_beams)
        encoded = self.encoder(scans).reshape(n, t, -1)
        return torch.cat([encoded, frames[..., self.num_beams :]], dim=-1)

    def q_from_features(self, features: Tensor) -> Tensor:
        """(N, k, D) features of one window -> (N, 3) Q values."""
        if self.lstm is None:
            return self.head(features[:, -1])  # type: ignore[no-any-return]
        return self.head(lstm_last_output(self.lstm, features))  # type: ignore[no-any-return]

    def forward(self, frames: Tensor) -> Tensor:
        return self.q_from_features(self.frame_features(frames))


def lstm_last_output(lstm: nn.LSTM, inputs: Tensor) -> Tensor:
    """The last output of a one-layer LSTM run from a zero state over (N, k, D) inputs.

    The same arithmetic as `nn.LSTM` (gate order i, f, g, o), written as plain matrix products so
    that the input projections of all k steps are one product, the first step's recurrent product
    (with a zero state) is skipped, and bfloat16 autocast applies to every product.
    """
    weight_ih, weight_hh, bias_ih, bias_hh = (
        cast(Tensor, getattr(lstm, name))
        for name in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0")
    )
    projected = inputs @ weight_ih.T + (bias_ih + bias_hh)
    hidden = cell = None
    for step in range(inputs.shape[1]):
        gates = projected[:, step]
        if hidden is not None:
            gates = gates + hidden @ weight_hh.T
        i, f, g, o = gates.chunk(4, dim=1)
        update = torch.sigmoid(i) * torch.tanh(g)
        cell = update if cell is None else torch.sigmoid(f) * cell + update
        hidden = torch.sigmoid(o) * torch.tanh(cell)
    assert hidden is not None
    return hidden
