"""The onboard policy runtime: load a policy file, carry each stream's state, return decisions.

One class, `PolicyRuntime`, serves the controller daemon, `qnav eval` of an exported file and
the playback tests. It never imports torch. The file's graph is one step of the policy: the
newest frame and the recurrent state in, Q values and the next state out (the state holds the
LSTM's (h, c) of the k-1 windows still in progress; docs/policy.md). Each decision of a stream
is the Q values of its window of the last k frames, exactly as if the window were run from a
zero state, with the window padded with the episode's first frame at the start (as
`contracts.observation.FrameWindow` pads it in training).

Two backends run the same file:

- onnxruntime (default): one intra-op thread, sequential execution, all graph optimisations.
- numpy: for boards without an onnxruntime wheel (32-bit ARM). It reads the weights from the
  ONNX file's initializers, which the exporter keeps under the training network's parameter
  names (`controller.onnx_file` parses the file without the onnx package, and dequantises the
  weights of an int8 file), and runs the same streaming arithmetic in float32.

Input rules (tested): a scan of the wrong length is refused with `PolicyInputError`; NaN and
+inf read as the maximum range, negative values and -inf as 0 (`contracts.observation`), so
Q values are never NaN; a non-finite target feature is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple, Protocol

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from qnav.contracts.actions import Action, TurnCommitment
from qnav.contracts.errors import PolicyFileError, PolicyInputError
from qnav.contracts.observation import TARGET_FEATURES, encode_frame
from qnav.contracts.policy_file import (
    CONV_LAYERS,
    CONV_STRIDE,
    FRAME_INPUT,
    OUTPUT_NAME,
    STATE_INPUTS,
    STATE_OUTPUTS,
    PolicyContract,
)
from qnav.controller.onnx_file import float_weights, read_onnx

Backend = Literal["onnxruntime", "numpy"]
BACKENDS: tuple[Backend, ...] = ("onnxruntime", "numpy")

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Expectation:
    """What the caller will feed; a policy file that does not fit is refused at load."""

    num_beams: int | None = None
    """Beams per scan the caller delivers (0: no lidar); None accepts the file's."""
    window_length: int | None = None
    """Frames per window the caller requires; None accepts the file's."""
    control_period_s: float | None = None
    """Control period the caller runs at; None accepts the file's."""


class Decision(NamedTuple):
    """The runtime's answer for one step of one stream."""

    action: Action
    """Greedy action."""
    q_values: F32
    """(3,) Q values, indexed by Action."""


class State(NamedTuple):
    """The recurrent state of N streams: slot j (from 0) holds the LSTM's hidden and cell state
    of the window that has consumed j + 1 frames."""

    h: F32
    """(N, k-1, H) hidden states."""
    c: F32
    """(N, k-1, H) cell states."""


class StepFunction(Protocol):
    """A backend: one frame per stream (N, F) and the state (None for a policy without one) ->
    Q values (N, 3) of the windows these frames complete, and the next state."""

    def __call__(self, frame: F32, state: State | None) -> tuple[F32, State | None]: ...


class OnnxRuntimeBackend:
    """The policy file run by onnxruntime on one thread."""

    def __init__(self, path: Path, contract: PolicyContract, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError:  # pragma: no cover - depends on the board
            raise PolicyFileError(
                "onnxruntime is not installed on this machine; use the numpy backend "
                "(--backend numpy)"
            ) from None
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(
                str(path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as error:  # onnxruntime raises its own exception types
            raise PolicyFileError(f"onnxruntime cannot load {path}: {error}") from None
        self.has_state = contract.has_state
        inputs = [FRAME_INPUT, *STATE_INPUTS] if self.has_state else [FRAME_INPUT]
        self.outputs = [OUTPUT_NAME, *STATE_OUTPUTS] if self.has_state else [OUTPUT_NAME]
        found = [i.name for i in self.session.get_inputs()]
        if found != inputs:
            raise PolicyFileError(
                f"{path}: the graph's inputs are {found}; its contract needs {inputs}"
            )

    def __call__(self, frame: F32, state: State | None) -> tuple[F32, State | None]:
        feeds = {FRAME_INPUT: frame}
        if state is not None:
            feeds |= {STATE_INPUTS[0]: state.h, STATE_INPUTS[1]: state.c}
        results = self.session.run(self.outputs, feeds)
        q = np.asarray(results[0], dtype=np.float32)
        if not self.has_state:
            return q, None
        return q, State(np.asarray(results[1]), np.asarray(results[2]))


class NumpyBackend:
    """The exported network's streaming arithmetic in numpy, weights taken from the file by
    name (the same operations as `training.networks.StreamingQNetwork`)."""

    def __init__(self, weights: dict[str, F32], contract: PolicyContract) -> None:
        def weight(name: str) -> F32:
            if name not in weights:
                raise PolicyFileError(
                    f"the policy file has no weight '{name}' (needed by the numpy backend)"
                )
            return np.ascontiguousarray(weights[name], dtype=np.float32)

        self.num_beams = contract.num_beams
        self.conv = (
            [
                (weight(f"encoder.layers.{2 * i}.weight"), weight(f"encoder.layers.{2 * i}.bias"))
                for i in range(CONV_LAYERS)
            ]
            if contract.num_beams
            else []
        )
        self.recurrent = contract.model_kind == "recurrent"
        if self.recurrent:
            self.input_weight = weight("lstm.weight_ih_l0").T.copy()
            self.lstm_bias = weight("lstm.bias_ih_l0") + weight("lstm.bias_hh_l0")
        if contract.has_state:  # a window of one frame never uses (nor stores) this matrix
            self.hidden_weight = weight("lstm.weight_hh_l0").T.copy()
            if self.hidden_weight.shape[0] != contract.state_size:
                raise PolicyFileError(
                    f"the policy file's LSTM has {self.hidden_weight.shape[0]} hidden units; "
                    f"its contract says state_size = {contract.state_size}"
                )
        self.hidden_layer = (weight("head.0.weight").T.copy(), weight("head.0.bias"))
        self.output_layer = (weight("head.2.weight").T.copy(), weight("head.2.bias"))

    def __call__(self, frame: F32, state: State | None) -> tuple[F32, State | None]:
        features = self._frame_features(frame)
        next_state = None
        if not self.recurrent:
            hidden = features
        elif state is None:  # a window of one frame: one step from the zero state
            hidden, _ = _lstm_cell(features @ self.input_weight + self.lstm_bias, None)
        else:
            hidden, next_state = self._lstm_stream_step(features, state)
        layer = np.maximum(hidden @ self.hidden_layer[0] + self.hidden_layer[1], 0.0)
        q: F32 = (layer @ self.output_layer[0] + self.output_layer[1]).astype(np.float32)
        return q, next_state

    def _frame_features(self, frame: F32) -> F32:
        if not self.conv:
            return frame
        n = frame.shape[0]
        x = frame[:, None, : self.num_beams]
        for kernel, bias in self.conv:
            out_channels, in_channels, width = kernel.shape
            # (N, C, L_out, K) windows -> (N, L_out, C*K) @ (C*K, O) -> (N, O, L_out)
            windows = sliding_window_view(x, width, axis=2)[:, :, ::CONV_STRIDE, :]
            patches = windows.transpose(0, 2, 1, 3).reshape(n, -1, in_channels * width)
            x = np.maximum(
                (patches @ kernel.reshape(out_channels, -1).T + bias).transpose(0, 2, 1), 0.0
            )
        return np.concatenate([x.reshape(n, -1), frame[:, self.num_beams :]], axis=-1)

    def _lstm_stream_step(self, features: F32, state: State) -> tuple[F32, State]:
        # The input projection once for every slot; one recurrent product for all slots (the
        # matrix is read once: N * (k-1) rows as one matrix, not a product per stream).
        projected = features @ self.input_weight + self.lstm_bias
        n, slots, size = state.h.shape
        recurrent = (state.h.reshape(n * slots, size) @ self.hidden_weight).reshape(n, slots, -1)
        started_h, started_c = _lstm_cell(projected, None)
        advanced_h, advanced_c = _lstm_cell(projected[:, None, :] + recurrent, state.c)
        next_state = State(
            np.concatenate([started_h[:, None], advanced_h[:, :-1]], axis=1),
            np.concatenate([started_c[:, None], advanced_c[:, :-1]], axis=1),
        )
        return advanced_h[:, -1], next_state


def _lstm_cell(gates: F32, cell: F32 | None) -> tuple[F32, F32]:
    """One LSTM step from the gates' pre-activations (..., 4H), torch's gate order (i, f, g, o),
    and the previous cell state (None: the zero state) -> (h, c)."""
    i, f, g, o = np.split(gates, 4, axis=-1)
    update = _sigmoid(i) * np.tanh(g)
    cell = update if cell is None else _sigmoid(f) * cell + update
    hidden: F32 = _sigmoid(o) * np.tanh(cell)
    return hidden, cell


def _sigmoid(x: F32) -> F32:
    # tanh form: no overflow warnings for large |x|, and exact to float32 rounding.
    result: F32 = (0.5 * (np.tanh(0.5 * x) + 1.0)).astype(np.float32, copy=False)
    return result


class PolicyRuntime:
    """A policy file ready to act: its contract, a backend and each stream's recurrent state.

    `num_streams` > 1 runs several independent episodes at once (simulated evaluation); the car
    uses one stream. After `reset`, a stream's next decision sees a window padded with its
    first frame, as in training.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        backend: Backend = "onnxruntime",
        num_streams: int = 1,
        expect: Expectation | None = None,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise PolicyFileError(f"policy file {self.path} does not exist")
        if backend not in BACKENDS:
            raise PolicyFileError(f"backend {backend!r} is not one of {', '.join(BACKENDS)}")
        contents = read_onnx(self.path)
        self.contract = PolicyContract.from_metadata(contents.metadata, str(self.path))
        _check_fits(self.contract, expect or Expectation(), self.path)
        _check_actions(self.contract, self.path)
        self.backend_name = backend
        self.step_function: StepFunction = (
            OnnxRuntimeBackend(self.path, self.contract)
            if backend == "onnxruntime"
            else NumpyBackend(float_weights(contents.initializers), self.contract)
        )
        self.state = self.zero_state(num_streams)
        self.fresh = np.ones(num_streams, dtype=bool)
        """Streams whose next frame begins an episode."""
        self.turns = TurnCommitment(num_streams) if self.contract.turn_commitment else None
        """Each stream's last decision, with the contract's `turn_commitment`."""

    @property
    def num_streams(self) -> int:
        """Independent streams kept."""
        return self.fresh.shape[0]

    def zero_state(self, num_streams: int) -> State | None:
        """The state of `num_streams` streams before any frame (None: the policy has none)."""
        if not self.contract.has_state:
            return None
        shape = (num_streams, self.contract.state_slots, self.contract.state_size)
        return State(np.zeros(shape, dtype=np.float32), np.zeros(shape, dtype=np.float32))

    def reset(self, streams: NDArray[np.intp] | None = None) -> None:
        """Start new episodes in `streams` (all by default): their windows restart."""
        self.fresh[slice(None) if streams is None else streams] = True
        if self.turns is not None:
            self.turns.restart(slice(None) if streams is None else streams)

    def step_batch(
        self, scan_m: NDArray[np.floating] | None, target_features: NDArray[np.floating]
    ) -> tuple[NDArray[np.int64], F32]:
        """Push one observation per stream and decide: actions (N,) and Q values (N, 3)."""
        frames = self.encode(scan_m, target_features)
        if self.fresh.any():
            self._prime(frames)
        q, self.state = self.step_function(frames, self.state)
        actions = q.argmax(axis=1)
        return (actions if self.turns is None else self.turns(actions)), q

    def step(
        self, scan_m: NDArray[np.floating] | None, target_features: NDArray[np.floating]
    ) -> Decision:
        """One stream: push a scan (B,) in metres (None without a lidar) and target features
        (distance m, sin, cos of bearing), and decide."""
        if self.num_streams != 1:
            raise PolicyInputError("step() serves one stream; use step_batch()")
        actions, q = self.step_batch(
            None if scan_m is None else np.asarray(scan_m)[None],
            np.asarray(target_features)[None],
        )
        return Decision(Action(int(actions[0])), q[0])

    def window_q_values(self, windows: F32) -> F32:
        """Q values of whole windows (N, k, F) of encoded frames, oldest first: each window's
        frames fed one by one from the zero state (k frames flush any state). The streams'
        own states are left as they are."""
        if windows.ndim != 3 or windows.shape[1:] != (
            self.contract.window_length,
            self.contract.frame_size,
        ):
            raise PolicyInputError(
                f"windows have shape {windows.shape}; expected (N, {self.contract.window_length}, "
                f"{self.contract.frame_size})"
            )
        state = self.zero_state(windows.shape[0])
        q = np.empty((windows.shape[0], 0), dtype=np.float32)
        for t in range(windows.shape[1]):
            q, state = self.step_function(np.ascontiguousarray(windows[:, t]), state)
        return q

    def _prime(self, frames: F32) -> None:
        """Give fresh streams the state of a window padded with their first frame.

        From the zero state, m feeds of one frame leave slot j holding min(j + 1, m) copies of
        it, so after k-1 feeds slot j holds j + 1 copies; this step then feeds the frame once
        more and completes the window of k copies, and the next frames see the padded windows
        that follow: FrameWindow's padding. Fresh streams are primed as one smaller batch.
        """
        if self.state is not None:
            fresh = np.flatnonzero(self.fresh)
            every = fresh.size == self.num_streams
            first = frames if every else frames[fresh]
            state = self.zero_state(first.shape[0])
            for _ in range(self.contract.state_slots):
                _, state = self.step_function(first, state)
            assert state is not None
            if every:
                self.state = state
            else:
                self.state.h[fresh], self.state.c[fresh] = state.h, state.c
        self.fresh[:] = False

    def encode(
        self, scan_m: NDArray[np.floating] | None, target_features: NDArray[np.floating]
    ) -> F32:
        """Check one observation per stream and encode it as frames (N, F)."""
        n, beams = self.num_streams, self.contract.num_beams
        features = np.asarray(target_features, dtype=np.float64)
        if features.shape != (n, TARGET_FEATURES):
            raise PolicyInputError(
                f"target features have shape {features.shape}; expected ({n}, {TARGET_FEATURES})"
            )
        if not np.isfinite(features).all():
            raise PolicyInputError("target features contain NaN or inf")
        if beams == 0:
            if scan_m is not None:
                raise PolicyInputError("this policy takes no lidar scan; pass None")
            return encode_frame(None, features, self.contract.max_range_m)
        if scan_m is None:
            raise PolicyInputError(f"this policy needs a {beams}-beam scan")
        scan = np.asarray(scan_m)
        if scan.shape != (n, beams):
            raise PolicyInputError(
                f"scan has shape {scan.shape}; this policy takes {beams} beams per scan "
                f"(expected ({n}, {beams}))"
            )
        return encode_frame(scan, features, self.contract.max_range_m)


def _check_actions(contract: PolicyContract, path: Path) -> None:
    """Every action's velocity is finite: the file's metadata is JSON, which Python reads with
    NaN and Infinity, and a command that is not a number is no command anyone meant."""
    bad = [
        f"{action.name.lower()} = ({v.linear_mps}, {v.angular_radps})"
        for action, v in zip(Action, contract.actions, strict=True)
        if not (math.isfinite(v.linear_mps) and math.isfinite(v.angular_radps))
    ]
    if bad:
        raise PolicyFileError(
            f"{path}: qnav.actions has velocities that are not finite: {', '.join(bad)}"
        )


def _check_fits(contract: PolicyContract, expect: Expectation, path: Path) -> None:
    mismatches = [
        f"{name} is {found} in the file but {wanted} here"
        for name, found, wanted in (
            ("num_beams", contract.num_beams, expect.num_beams),
            ("window_length", contract.window_length, expect.window_length),
            ("control_period_s", contract.control_period_s, expect.control_period_s),
        )
        if wanted is not None and found != wanted
    ]
    if mismatches:
        raise PolicyFileError(f"{path} does not fit: " + "; ".join(mismatches))
