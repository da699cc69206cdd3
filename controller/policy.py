"""The onboard policy runtime: load a policy file, keep the k-frame window, return decisions.

One class, `PolicyRuntime`, serves the controller daemon, `qnav eval` of an exported file and
the playback tests. It never imports torch. Two backends run the same file:

- onnxruntime (default): one intra-op thread, sequential execution, all graph optimisations.
- numpy: for boards without an onnxruntime wheel (32-bit ARM). It reads the weights from the
  ONNX file's initializers, which the exporter keeps under the training network's parameter
  names (`controller.onnx_file` parses the file without the onnx package), and runs the same
  arithmetic in float32.

Input rules (tested): a scan of the wrong length is refused with `PolicyInputError`; NaN and
+inf read as the maximum range, negative values and -inf as 0 (`contracts.observation`), so
Q values are never NaN; a non-finite target feature is refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple, Protocol

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from contracts.actions import Action
from contracts.errors import PolicyFileError, PolicyInputError
from contracts.observation import TARGET_FEATURES, FrameWindow, encode_frame
from contracts.policy_file import CONV_LAYERS, CONV_STRIDE, INPUT_NAME, OUTPUT_NAME, PolicyContract
from controller.onnx_file import read_onnx

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


class QFunction(Protocol):
    """A backend: a batch of windows (N, k, F) -> Q values (N, 3)."""

    def __call__(self, frames: F32) -> F32: ...


class OnnxRuntimeBackend:
    """The policy file run by onnxruntime on one thread."""

    def __init__(self, path: Path, threads: int = 1) -> None:
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

    def __call__(self, frames: F32) -> F32:
        (q,) = self.session.run([OUTPUT_NAME], {INPUT_NAME: frames})
        return np.asarray(q, dtype=np.float32)


class NumpyBackend:
    """The exported network's arithmetic in numpy, weights taken from the file by name."""

    def __init__(self, weights: dict[str, NDArray[np.generic]], contract: PolicyContract) -> None:
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
            self.hidden_weight = weight("lstm.weight_hh_l0").T.copy()
            self.lstm_bias = weight("lstm.bias_ih_l0") + weight("lstm.bias_hh_l0")
        self.hidden_layer = (weight("head.0.weight").T.copy(), weight("head.0.bias"))
        self.output_layer = (weight("head.2.weight").T.copy(), weight("head.2.bias"))

    def __call__(self, frames: F32) -> F32:
        features = self._frame_features(frames)
        hidden = self._lstm_last_output(features) if self.recurrent else features[:, -1]
        layer = np.maximum(hidden @ self.hidden_layer[0] + self.hidden_layer[1], 0.0)
        q: F32 = (layer @ self.output_layer[0] + self.output_layer[1]).astype(np.float32)
        return q

    def _frame_features(self, frames: F32) -> F32:
        if not self.conv:
            return frames
        n, t, _ = frames.shape
        x = frames[..., : self.num_beams].reshape(n * t, 1, self.num_beams)
        for kernel, bias in self.conv:
            out_channels, in_channels, width = kernel.shape
            # (M, C, L_out, K) windows -> (M, L_out, C*K) @ (C*K, O) -> (M, O, L_out)
            windows = sliding_window_view(x, width, axis=2)[:, :, ::CONV_STRIDE, :]
            patches = windows.transpose(0, 2, 1, 3).reshape(n * t, -1, in_channels * width)
            x = np.maximum(
                (patches @ kernel.reshape(out_channels, -1).T + bias).transpose(0, 2, 1), 0.0
            )
        encoded = x.reshape(n, t, -1)
        return np.concatenate([encoded, frames[..., self.num_beams :]], axis=-1)

    def _lstm_last_output(self, features: F32) -> F32:
        # The gate order and zero initial state of torch.nn.LSTM (i, f, g, o).
        projected = features @ self.input_weight + self.lstm_bias
        hidden = cell = None
        for step in range(features.shape[1]):
            gates = projected[:, step]
            if hidden is not None:
                gates = gates + hidden @ self.hidden_weight
            i, f, g, o = np.split(gates, 4, axis=1)
            update = _sigmoid(i) * np.tanh(g)
            cell = update if cell is None else _sigmoid(f) * cell + update
            hidden = _sigmoid(o) * np.tanh(cell)
        assert hidden is not None
        last: F32 = hidden
        return last


def _sigmoid(x: F32) -> F32:
    # tanh form: no overflow warnings for large |x|, and exact to float32 rounding.
    result: F32 = (0.5 * (np.tanh(0.5 * x) + 1.0)).astype(np.float32, copy=False)
    return result


class PolicyRuntime:
    """A policy file ready to act: its contract, a backend and one window per stream.

    `num_streams` > 1 runs several independent episodes at once (simulated evaluation); the car
    uses one stream. A stream's window restarts, padded with its first frame as in training,
    after `reset`.
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
        self.backend_name = backend
        self.q_function: QFunction = (
            OnnxRuntimeBackend(self.path)
            if backend == "onnxruntime"
            else NumpyBackend(contents.initializers, self.contract)
        )
        self.window = FrameWindow(
            num_streams, self.contract.frame_size, self.contract.window_length
        )

    @property
    def num_streams(self) -> int:
        """Independent windows kept."""
        return self.window.frames.shape[0]

    def reset(self, streams: NDArray[np.intp] | None = None) -> None:
        """Start new episodes in `streams` (all by default): their windows restart."""
        self.window.restart(streams)

    def step_batch(
        self, scan_m: NDArray[np.floating] | None, target_features: NDArray[np.floating]
    ) -> tuple[NDArray[np.int64], F32]:
        """Push one observation per stream and decide: actions (N,) and Q values (N, 3)."""
        q = self.q_function(self.window.advance(self.encode(scan_m, target_features)))
        return q.argmax(axis=1), q

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
