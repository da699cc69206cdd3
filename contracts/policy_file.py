"""The policy file's contract: what an exported ONNX policy takes, returns and promises.

The exporter writes a `PolicyContract` into the ONNX file's metadata; the onboard runtime reads
it back and configures itself from it (window length, beams, range scaling, control period,
what each action means in m/s and rad/s), refusing a file that lacks it or does not fit.

The graph takes the newest frame produced by `contracts.observation.encode_frame` (scans in
metres and target features go in there, and nowhere else, to be scaled and cleaned of inf and
NaN) and, for a recurrent policy, the state the previous step returned: the LSTM's (h, c) of
the k-1 windows still in progress. It returns the Q value of each action of
`contracts.actions.Action` for the window that ends with this frame, and the next state. Every
window still starts from a zero LSTM state, as in the paper; carrying the partial windows only
avoids recomputing them (docs/policy.md, "Why a streaming graph").
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from qnav.contracts.actions import NUM_ACTIONS, Action
from qnav.contracts.errors import ConfigError, PolicyFileError
from qnav.contracts.motion import Dynamics, IncrementDynamics, InertiaDynamics
from qnav.contracts.observation import TARGET_FEATURES

POLICY_FORMAT = "qnav-policy/2"
"""Value of the `qnav.format` metadata key; a new major number means an incompatible layout.
/2: the streaming graph (newest frame and carried state in). /1 was the whole-window graph."""

WINDOW_FORMAT = "qnav-policy/1"
"""The earlier layout (input: the whole window of k frames); refused, with the fix named."""

FRAME_INPUT = "frame"
"""The graph's first input: (batch, frame_size) float32, the newest encoded frame."""

STATE_INPUTS = ("state_h", "state_c")
"""The recurrent state in, (batch, state_slots, state_size) float32 each: slot j (from 0) holds
the LSTM's hidden and cell state of the window that has consumed j + 1 frames. Absent when the
policy has no state (feedforward, or a window of one frame)."""

OUTPUT_NAME = "q_values"
"""The graph's first output: (batch, 3) float32 Q values, indexed by `Action`."""

STATE_OUTPUTS = ("next_state_h", "next_state_c")
"""The state to feed with the next frame, shaped as `STATE_INPUTS`."""

BEAM_CONVENTION = "ccw-from-heading-0-to-2pi"
"""Beam i points at i * 2*pi / num_beams radians, counter-clockwise from the robot's heading."""

METADATA_PREFIX = "qnav."

WEIGHT_TYPES = ("float32", "int8")
"""How a file stores its large weights: float32, or int8 (the LSTM's two matrices and the hidden
layer quantised per output column, a quarter of the bytes; docs/policy.md, "int8 weights")."""

QUANTIZED_SUFFIXES = ("_quantized", "_scale", "_zero_point")
"""An int8 weight W is stored as three initializers W_quantized (int8, (K, N)), W_scale and
W_zero_point (per column, (N,)): W = (W_quantized - W_zero_point) * W_scale. onnxruntime's
quantiser writes these names."""

TRANSPOSED_SUFFIX = "_Transposed"
"""An initializer named P_Transposed holds the transpose of the training parameter P (the
products of an int8 file take their weights as (in, out))."""

ENTRIES_ADDED_LATER = ("weight_type", "motion", "turn_commitment")
"""Contract fields added after files of this format were written: a file without the entry gets
the field's default (weight_type: float32, all such files have float32 weights; motion: empty,
so the onboard look-ahead refuses the file until it is exported again; turn_commitment: off)."""

CONV_LAYERS, CONV_CHANNELS, CONV_KERNEL, CONV_STRIDE = 3, 8, 6, 3
"""The paper's lidar encoder (3 x Conv1d, 8 channels, kernel 6, stride 3): the training network
is built from these, and the numpy backend runs the file's weights with them."""


@dataclass(frozen=True)
class ActionVelocity:
    """What one action commands, as a body velocity (REP 103: x forward, z up)."""

    linear_mps: float
    """Forward speed commanded."""
    angular_radps: float
    """Turn rate commanded, counter-clockwise positive."""


@dataclass(frozen=True)
class PolicyContract:
    """Everything the runtime needs to feed a policy file and act on its output."""

    model_kind: str
    """recurrent (LSTM over the window) or feedforward (last frame only)."""
    window_length: int
    """Frames per input (the paper's k)."""
    num_beams: int
    """Lidar beams per frame; 0 for the lidar-less (pose and target only) policy."""
    max_range_m: float
    """Range that scans and target distances are divided by."""
    control_period_s: float
    """Time between decisions the policy was trained with."""
    actions: tuple[ActionVelocity, ...]
    """Velocity commanded by each action, in `Action` order (forward, left, right)."""
    dynamics: str
    """Dynamics model of the training world (inertia or increment)."""
    scenario: str
    """Name of the training world."""
    training_run: str
    """Run folder the weights came from."""
    commit: str
    """Source revision the policy was trained (or, failing that, exported) with."""
    state_slots: int
    """Partial windows carried between steps (k - 1 for the recurrent policy, else 0)."""
    state_size: int
    """Values per slot of each of h and c (the LSTM's hidden size; 0 without a state)."""
    evaluation: Mapping[str, float] = field(default_factory=dict)
    """Test-protocol results of this file (success, collision, unfinished, episodes; for an
    int8 file also agreement_with_float32, the share of its decisions that the float32 network
    takes too)."""
    weight_type: str = "float32"
    """How the large weights are stored: float32, or int8 (`WEIGHT_TYPES`)."""
    motion: Mapping[str, Any] = field(default_factory=dict)
    """The training world's motion model, which the onboard look-ahead forecasts with:
    `dynamics` (the fields of `contracts.motion.InertiaDynamics` or `IncrementDynamics`) and
    `robot_radius_m` (the paper's l); empty in files exported before it existed."""
    turn_commitment: bool = False
    """The runtime never reverses the turn of its previous decision (left then right, or right
    then left) before a forward decision: a policy imitating a planner it cannot see dithers
    between turns on the spot where the two are close (`qnav export --turn-commitment`)."""
    beam_convention: str = BEAM_CONVENTION
    """How beam indices map to angles."""
    format: str = POLICY_FORMAT
    """File layout version."""

    def __post_init__(self) -> None:
        if self.weight_type not in WEIGHT_TYPES:
            raise PolicyFileError(
                f"weight_type = {self.weight_type!r} is not one of {', '.join(WEIGHT_TYPES)}"
            )
        slots = self.window_length - 1 if self.model_kind == "recurrent" else 0
        if self.state_slots != slots or (self.state_size > 0) != (slots > 0):
            raise PolicyFileError(
                f"state_slots = {self.state_slots} and state_size = {self.state_size} do not fit "
                f"a {self.model_kind} policy with window_length = {self.window_length} (expected "
                f"{slots} slots{', each of positive size' if slots else ' and size 0'})"
            )
        if len(self.actions) != NUM_ACTIONS:
            raise PolicyFileError(
                f"actions lists {len(self.actions)} velocities; the action table has "
                f"{NUM_ACTIONS} ({', '.join(a.name.lower() for a in Action)})"
            )

    @property
    def has_state(self) -> bool:
        """Whether the graph takes and returns a recurrent state."""
        return self.state_slots > 0

    def motion_model(self, source: str) -> tuple[Dynamics, float]:
        """The training world's dynamics and robot radius (`motion`); `source` names the file in
        the error raised when the file predates the entry or it is malformed."""
        if not self.motion:
            raise PolicyFileError(
                f"{source} carries no motion model (exported before the look-ahead existed): "
                "export it again with `qnav export`"
            )
        try:
            settings = dict(self.motion["dynamics"])
            kind = settings.get("kind")
            dynamics: Dynamics
            if kind == "inertia":
                dynamics = InertiaDynamics(**settings)
            elif kind == "increment":
                dynamics = IncrementDynamics(**settings)
            else:
                raise PolicyFileError(f"{source}: motion dynamics kind {kind!r} is unknown")
            return dynamics, float(self.motion["robot_radius_m"])
        except (KeyError, TypeError, ValueError, ConfigError) as error:
            raise PolicyFileError(f"{source}: malformed motion metadata: {error}") from None

    @property
    def frame_size(self) -> int:
        """Values per encoded frame: the beams, then the target features."""
        return self.num_beams + TARGET_FEATURES

    def to_metadata(self) -> dict[str, str]:
        """ONNX metadata entries: one `qnav.<field>` key per field, each value JSON."""
        return {METADATA_PREFIX + name: json.dumps(value) for name, value in asdict(self).items()}

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str], source: str) -> PolicyContract:
        """Read the contract back; `source` names the file in errors."""
        if METADATA_PREFIX + "format" not in metadata:
            raise PolicyFileError(
                f"{source} is not a qnav policy: its metadata has no '{METADATA_PREFIX}format' "
                "entry (export policies with `qnav export`)"
            )
        found = metadata[METADATA_PREFIX + "format"]
        check_format(found, source)
        values = metadata_values(cls, metadata, source, ENTRIES_ADDED_LATER)
        try:
            values["actions"] = tuple(ActionVelocity(**a) for a in values["actions"])
            return cls(**values)
        except TypeError as error:
            raise PolicyFileError(f"{source}: malformed metadata: {error}") from None


def metadata_values(
    contract: type[Any], metadata: Mapping[str, str], source: str, added_later: tuple[str, ...] = ()
) -> dict[str, Any]:
    """Each field of the dataclass `contract` from its `qnav.<field>` JSON entry (a field in
    `added_later` may be absent: the file predates it, and the field keeps its default);
    PolicyFileError naming `source` and the entry otherwise."""
    values: dict[str, Any] = {}
    for spec in fields(contract):
        key = METADATA_PREFIX + spec.name
        if key not in metadata and spec.name in added_later:
            continue
        if key not in metadata:
            raise PolicyFileError(f"{source} lacks the metadata entry '{key}'")
        try:
            values[spec.name] = json.loads(metadata[key])
        except json.JSONDecodeError as error:
            raise PolicyFileError(f"{source}: metadata '{key}' is not JSON: {error}") from None
    return values


def check_format(found: str, source: str) -> None:
    """Refuse any `qnav.format` value (JSON, as stored) but this runtime's, naming the fix."""
    try:
        value = json.loads(found)
    except json.JSONDecodeError:
        value = found
    if value == POLICY_FORMAT:
        return
    if value == WINDOW_FORMAT:
        raise PolicyFileError(
            f"{source} has policy format {WINDOW_FORMAT!r} (a graph over the whole window of "
            f"frames); this runtime reads {POLICY_FORMAT!r} (the newest frame and the carried "
            "state). Re-export it: `qnav export RUN -o FILE` from its training run, or "
            "`qnav export OLD.onnx -o NEW.onnx` from the old file's own weights"
        )
    raise PolicyFileError(
        f"{source} has policy format {found}; this runtime reads {POLICY_FORMAT!r} "
        "(export the policy again with this version's `qnav export`)"
    )
