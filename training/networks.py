"""The paper's Q-networks, recurrent and feedforward, with or without the lidar encoder.

Input: a window of encoded frames (N, k, F) from `contracts.observation.encode_frame`, each
frame the scaled scan (B values, absent for the toy car) followed by the scaled target features
(3 values) and, for a network given obstacle inputs (beyond the paper), the encoded obstacles
(`contracts.observation.obstacle_features`). Output: Q values (N, 3).

`StreamingQNetwork` is the same network as the onboard runtime steps it (and as it is exported):
the newest frame and the k-1 partial windows in progress in, the Q values of the window that
the frame completes and the next partial windows out. The arithmetic is the window's.
"""

from __future__ import annotations

from typing import cast

import torch
from torch import Tensor, nn
from torch.nn import functional

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.observation import TARGET_FEATURES
from qnav.contracts.policy_file import CONV_CHANNELS, CONV_KERNEL, CONV_LAYERS, CONV_STRIDE
from qnav.sim.config import WorldConfig
from qnav.training.config import ModelKind, TrainSettings


def conv_output_length(num_beams: int) -> int:
    """Length of the lidar encoder's output per channel."""
    length = num_beams
    for _ in range(CONV_LAYERS):
        length = (length - CONV_KERNEL) // CONV_STRIDE + 1
    return length


class LidarEncoder(nn.Module):
    """3 x Conv1d(8 channels, kernel 6, stride 3) + ReLU over a scan: (M, B) -> (M, 8 * L),
    the encoder policy files fix (`contracts.policy_file`)."""

    def __init__(self, num_beams: int) -> None:
        super().__init__()
        if conv_output_length(num_beams) < 1:
            raise ValueError(
                f"num_beams = {num_beams} is too few for three stride-{CONV_STRIDE} convolutions"
            )
        self.layers = conv_layers(CONV_CHANNELS)
        self.output_size = CONV_CHANNELS * conv_output_length(num_beams)

    def forward(self, scans: Tensor) -> Tensor:
        """(M, B) scans -> (M, output_size)."""
        return self.layers(scans.unsqueeze(1)).flatten(1)  # type: ignore[no-any-return]


def conv_layers(channels: int) -> nn.Sequential:
    """The encoder's three convolutions (kernel 6, stride 3), each followed by a ReLU, with
    `channels` outputs each (policy files fix 8)."""
    layers: list[nn.Module] = []
    previous = 1
    for _ in range(CONV_LAYERS):
        layers += [nn.Conv1d(previous, channels, CONV_KERNEL, CONV_STRIDE), nn.ReLU()]
        previous = channels
    return nn.Sequential(*layers)


def channel_activity(encoder: LidarEncoder, scans: Tensor) -> list[Tensor]:
    """Per convolution (after its ReLU), each channel's share of (scan, position) pairs where it
    is positive: 0 is a dead channel (no gradient passes it), 1 a linear one."""
    activity = []
    with torch.no_grad():
        x = scans.unsqueeze(1)
        for layer in encoder.layers:
            x = layer(x)
            if isinstance(layer, nn.ReLU):
                activity.append((x > 0).float().mean(dim=(0, 2)))
    return activity


class QNetwork(nn.Module):
    """Frames -> per-frame features -> LSTM over the window (or the last frame alone) -> Q.

    recurrent:   features -> LSTM(hidden) -> Linear(hidden) + ReLU -> Linear(3)
    feedforward: features of the last frame -> Linear(hidden) + ReLU -> Linear(3)
    The LSTM starts from a zero state on every window, as in the paper.
    """

    def __init__(
        self,
        kind: ModelKind,
        num_beams: int | None,
        hidden_size: int = 512,
    ) -> None:
        super().__init__()
        self.kind: ModelKind = kind
        self.num_beams = num_beams or 0
        self.hidden_size = hidden_size
        self.encoder = LidarEncoder(num_beams) if num_beams else None
        self.feature_size = (
            (self.encoder.output_size if self.encoder else 0) + self.frame_size - self.num_beams
        )
        self.lstm = (
            nn.LSTM(self.feature_size, hidden_size, batch_first=True)
            if kind == "recurrent"
            else None
        )
        head_input = self.summary_size
        self.head = nn.Sequential(
            nn.Linear(head_input, hidden_size), nn.ReLU(), nn.Linear(hidden_size, NUM_ACTIONS)
        )

    @property
    def frame_size(self) -> int:
        """Values per input frame."""
        return self.num_beams + TARGET_FEATURES

    def frame_features(self, frames: Tensor) -> Tensor:
        """(N, T, F) frames -> (N, T, D) features; the encoder runs once per frame."""
        return frame_features(self.encoder, self.num_beams, frames)

    @property
    def summary_size(self) -> int:
        """Values in the window's summary (`window_summary`)."""
        return self.hidden_size if self.lstm is not None else self.feature_size

    def window_summary(self, features: Tensor) -> Tensor:
        """(N, k, D) features of one window -> what the head reads (N, S): the LSTM's last
        output, or the last frame's features for the feedforward network."""
        if self.lstm is None:
            return features[:, -1]
        return lstm_last_output(self.lstm, features)

    def q_from_features(self, features: Tensor) -> Tensor:
        """(N, k, D) features of one window -> (N, 3) Q values."""
        return self.head(self.window_summary(features))  # type: ignore[no-any-return]

    def forward(self, frames: Tensor) -> Tensor:
        return self.q_from_features(self.frame_features(frames))


class StreamingQNetwork(nn.Module):
    """A QNetwork stepped one frame at a time, carrying the windows still in progress.

    forward(frame (N, F), state_h, state_c (N, k-1, H)) -> (q (N, 3), next_h, next_c), where
    slot j (from 0) of the state holds the LSTM's (h, c) of the window that has consumed j + 1
    frames. A step advances every slot by the frame, so the last slot completes a window of k
    frames (its Q values are returned), and the window that starts at the frame (one step from
    the zero state) becomes slot 0. Feeding k frames from any state gives exactly the window
    network's Q values on them. Without a state (feedforward, or k = 1) it is forward(frame) ->
    (q,).

    It holds the QNetwork's own modules under the same names, so that its parameters (and the
    exported file's initializers) are named as the QNetwork's: the numpy backend reads them.
    """

    def __init__(self, network: QNetwork, window_length: int) -> None:
        super().__init__()
        self.num_beams = network.num_beams
        self.encoder = network.encoder
        self.lstm = network.lstm
        self.head = network.head
        self.state_slots = window_length - 1 if network.lstm is not None else 0
        self.state_size = network.hidden_size if self.state_slots else 0

    def forward(
        self, frame: Tensor, state_h: Tensor | None = None, state_c: Tensor | None = None
    ) -> tuple[Tensor, ...]:
        features = frame
        if self.encoder is not None:  # one frame: no time axis to fold into the batch
            beams = self.num_beams
            features = torch.cat([self.encoder(frame[:, :beams]), frame[:, beams:]], dim=-1)
        if self.lstm is None:
            return (self.head(features),)
        if not self.state_slots:
            hidden, _ = lstm_cell(lstm_input_projection(self.lstm, features), None)
            return (self.head(hidden),)
        if state_h is None or state_c is None:
            raise ValueError(f"this network steps {self.state_slots} partial windows: pass them")
        complete, next_h, next_c = lstm_stream_step(self.lstm, features, state_h, state_c)
        return self.head(complete), next_h, next_c


def frame_features(encoder: LidarEncoder | None, num_beams: int, frames: Tensor) -> Tensor:
    """(N, T, F) frames -> (N, T, D) features: each frame's scan through the encoder, followed
    by the rest of the frame (target features, and obstacles where given)."""
    if encoder is None:
        return frames
    n, t, _ = frames.shape
    encoded = encoder(frames[..., :num_beams].reshape(n * t, num_beams)).reshape(n, t, -1)
    return torch.cat([encoded, frames[..., num_beams:]], dim=-1)


def _lstm_weights(lstm: nn.LSTM) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    weight_ih, weight_hh, bias_ih, bias_hh = (
        cast(Tensor, getattr(lstm, name))
        for name in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0")
    )
    return weight_ih, weight_hh, bias_ih, bias_hh


def lstm_input_projection(lstm: nn.LSTM, inputs: Tensor) -> Tensor:
    """The gates' input part, both biases included: (..., D) -> (..., 4H)."""
    weight_ih, _, bias_ih, bias_hh = _lstm_weights(lstm)
    return inputs @ weight_ih.T + (bias_ih + bias_hh)


def lstm_cell(gates: Tensor, cell: Tensor | None) -> tuple[Tensor, Tensor]:
    """One LSTM step from its gate pre-activations (..., 4H) in torch's order (i, f, g, o) and
    the previous cell state (None: the zero state, whose products are skipped) -> (h, c)."""
    # Slices, not chunk(): the ONNX exporter turns chunk into a sequence and seven ops.
    size = gates.shape[-1] // 4
    i, f, g, o = (gates[..., k * size : (k + 1) * size] for k in range(4))
    update = torch.sigmoid(i) * torch.tanh(g)
    cell = update if cell is None else torch.sigmoid(f) * cell + update
    return torch.sigmoid(o) * torch.tanh(cell), cell


def lstm_stream_step(
    lstm: nn.LSTM, inputs: Tensor, state_h: Tensor, state_c: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """One frame's features (N, D) into the partial windows (N, S, H) of `StreamingQNetwork`:
    the output of the window this frame completes (N, H) and the next partial windows.

    The input projection is computed once for all slots, and all slots share one recurrent
    product (N * S rows against the recurrent matrix, read once). The window that starts at
    this frame is one more slot, in front, with a zero state: its recurrent product and its
    forget gate's product are exactly zero, so it gets the zero-state step exactly, and every
    slot goes through one cell (a short graph when exported).
    """
    _, weight_hh, _, _ = _lstm_weights(lstm)
    projected = lstm_input_projection(lstm, inputs)
    previous_h = functional.pad(state_h, (0, 0, 1, 0))  # (N, S + 1, H), zero state in front
    previous_c = functional.pad(state_c, (0, 0, 1, 0))
    hidden, cell = lstm_cell(projected.unsqueeze(1) + previous_h @ weight_hh.T, previous_c)
    return hidden[:, -1], hidden[:, :-1], cell[:, :-1]


def lstm_last_output(lstm: nn.LSTM, inputs: Tensor) -> Tensor:
    """The last output of a one-layer LSTM run from a zero state over (N, k, D) inputs.

    The same arithmetic as `nn.LSTM` (gate order i, f, g, o), written as plain matrix products so
    that the input projections of all k steps are one product, the first step's recurrent product
    (with a zero state) is skipped, and bfloat16 autocast applies to every product.
    """
    _, weight_hh, _, _ = _lstm_weights(lstm)
    projected = lstm_input_projection(lstm, inputs)
    hidden = cell = None
    for step in range(inputs.shape[1]):
        gates = projected[:, step]
        if hidden is not None:
            gates = gates + hidden @ weight_hh.T
        hidden, cell = lstm_cell(gates, cell)
    assert hidden is not None
    return hidden


def make_network(world: WorldConfig, settings: TrainSettings) -> QNetwork:
    """The Q-network for this world and these settings (fresh weights)."""
    beams = world.lidar.num_beams if world.lidar else None
    return QNetwork(settings.model, beams, settings.hidden_size)
