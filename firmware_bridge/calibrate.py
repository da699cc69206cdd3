"""`qnav calibrate-car`: measure what a command does on the car, and set the bridge's scales.

It talks to a running `qnav bridge` over zenoh like the controller does: it publishes Twist
commands on `cmd_vel` and reads the vehicle's own velocity from `qnav/vehicle_state` (the
autopilot's LOCAL_POSITION_NED and ATTITUDE; indoors those come from motion capture). The
pattern is short and bounded: a few straight runs at fractions of the current full-throttle
scale, then a few turns, each `settle_s + measure_s` long, with the car stopped (by silence:
the bridge's failsafe) between runs; it aborts (stops publishing, so the bridge stops the car)
when the car goes farther than `max_distance_m` from where it started, and it never arms the
car: a person arms it and watches (supervised).

The fit is a line through the origin per axis (speed = k x throttle fraction, turn rate =
k x steering fraction): k is the new `output.speed_at_full_throttle_mps` /
`output.turn_rate_at_full_steering_radps`. It prints them as a TOML `[output]` section, and with
`--write` writes them into the bridge's settings file (`with_scales`).
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import from_dict
from qnav.contracts.transport import StoppedError, open_session
from qnav.contracts.wire import (
    COMMAND,
    VEHICLE_STATE,
    Twist2D,
    decode_json_msg,
    encode_twist_msg,
    key,
)
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.settings import BridgeSettings

log = logging.getLogger("qnav.firmware_bridge.calibrate")

COMMAND_PERIOD_S = 0.1
"""Commands go out at 10 Hz, as a controller's would."""


@dataclass(frozen=True)
class Pattern:
    """The calibration drive: what is commanded, for how long, and its bounds."""

    throttle_fractions: tuple[float, ...] = (0.2, 0.35, 0.5)
    """Straight runs at these fractions of full throttle (of the current scale)."""
    steering_fractions: tuple[float, ...] = (0.3, 0.6)
    """Turns at these fractions of full steering, left then right."""
    turn_throttle_fraction: float = 0.2
    """Throttle during the turns (a steered car turns only while it moves)."""
    settle_s: float = 1.5
    """Each run's first part, not measured (the car accelerates)."""
    measure_s: float = 1.5
    """Each run's measured part: the mean of the vehicle's velocity reports."""
    rest_timeout_s: float = 10.0
    """Between runs, wait this long at most for the car to come to rest."""
    max_distance_m: float = 15.0
    """Abort when the car is farther than this from where it started."""


class CalibrationAbortedError(RuntimeError):
    """The pattern was stopped (too far, no velocity reports, vehicle not armed, a signal)."""


def fit_through_origin(fractions: Sequence[float], measured: Sequence[float]) -> float:
    """Least-squares k of measured = k x fraction (what full travel gives)."""
    numerator = sum(f * m for f, m in zip(fractions, measured, strict=True))
    denominator = sum(f * f for f in fractions)
    if denominator <= 0:
        raise ValueError("no non-zero fraction to fit")
    return numerator / denominator


def output_section(speed_mps: float, turn_rate_radps: float) -> str:
    """The bridge settings the fit gives, as a TOML section."""
    return (
        "[output]\n"
        f"speed_at_full_throttle_mps = {speed_mps:.3f}\n"
        f"turn_rate_at_full_steering_radps = {turn_rate_radps:.3f}\n"
    )


SCALE_KEYS = ("speed_at_full_throttle_mps", "turn_rate_at_full_steering_radps")
"""The two `[output]` settings a calibration measures."""
_HEADER = re.compile(r"^\s*\[\s*(?P<name>[^]\s]+)\s*\]\s*(#.*)?$")


def with_scales(text: str, speed_mps: float, turn_rate_radps: float) -> str:
    """A bridge settings file's `text` with the two scales set in its `[output]` section
    (added after its header where missing, the section added where there is none); every
    other line, comments included, as it was."""
    values = dict(zip(SCALE_KEYS, (f"{speed_mps:.3f}", f"{turn_rate_radps:.3f}"), strict=True))
    lines = text.splitlines()
    section, header_at, written = "", None, set()
    for index, line in enumerate(lines):
        header = _HEADER.match(line)
        if header:
            section = header["name"]
            header_at = index if section == "output" else header_at
            continue
        name = line.split("=", 1)[0].strip()
        if section == "output" and "=" in line and name in values:
            lines[index] = f"{name} = {values[name]}"
            written.add(name)
    missing = [f"{name} = {value}" for name, value in values.items() if name not in written]
    if header_at is None:
        lines += ["", "[output]", *missing] if lines else ["[output]", *missing]
    else:
        lines[header_at + 1 : header_at + 1] = missing
    return "\n".join(lines) + "\n"


def write_scales(path: Path, speed_mps: float, turn_rate_radps: float) -> None:
    """`qnav calibrate-car --write`: the measured scales into the bridge's settings file, which
    is checked to read back with them before it replaces the old one (ConfigError if not)."""
    text = with_scales(load_text(path), speed_mps, turn_rate_radps)
    try:
        output = from_dict(BridgeSettings, tomllib.loads(text)).output
    except (tomllib.TOMLDecodeError, ConfigError) as error:
        raise ConfigError(f"{path}: the scales could not be written in ({error})") from None
    expected = (round(speed_mps, 3), round(turn_rate_radps, 3))
    if (output.speed_at_full_throttle_mps, output.turn_rate_at_full_steering_radps) != expected:
        raise ConfigError(f"{path}: its [output] section is not one the scales could go into")
    partial = path.with_name(path.name + ".calibrating")
    partial.write_text(text)
    partial.replace(path)


def load_text(path: Path) -> str:
    """A settings file's text, or a ConfigError saying why it cannot be read."""
    try:
        return path.read_text()
    except OSError as error:
        raise ConfigError(f"settings file {path} cannot be read: {error.strerror}") from None


class Calibrator:
    """Commands and state over one zenoh session."""

    def __init__(
        self, settings: BridgeSettings, pattern: Pattern, stop: threading.Event | None = None
    ) -> None:
        self.settings = settings
        self.pattern = pattern
        self._stop = stop or threading.Event()
        """Set (a signal): the pattern ends at once, and the bridge's failsafe stops the car."""
        namespace = settings.zenoh.namespace
        try:
            self._session: Any = open_session(settings.zenoh, self._stop)
        except StoppedError:
            raise CalibrationAbortedError("stopped before zenoh was joined") from None
        self._publisher = self._session.declare_publisher(key(COMMAND, namespace))
        self._lock = threading.Lock()
        self._states: list[tuple[float, dict[str, Any]]] = []
        self._subscriber = self._session.declare_subscriber(
            key(VEHICLE_STATE, namespace), self._on_state
        )
        self._start: tuple[float, float] | None = None

    def close(self) -> None:
        self._subscriber.undeclare()
        self._session.close()

    def _on_state(self, sample: Any) -> None:
        try:
            state = decode_json_msg(sample.payload.to_bytes())
        except Exception:  # a malformed state is no reading
            return
        with self._lock:
            self._states.append((time.monotonic(), state))
            del self._states[:-2000]

    def state(self) -> dict[str, Any]:
        with self._lock:
            return self._states[-1][1] if self._states else {}

    def _velocities(self, since_s: float) -> list[dict[str, float]]:
        with self._lock:
            return [s["velocity"] for t, s in self._states if t >= since_s and s.get("velocity")]

    def _pause(self, seconds: float) -> None:
        """Sleep, or end the pattern if a stop was asked for meanwhile."""
        if self._stop.wait(seconds):
            raise CalibrationAbortedError("stopped (SIGINT or SIGTERM); nothing measured")

    def wait_ready(self, timeout_s: float) -> None:
        """Until the bridge reports the link up, the car armed and its velocity."""
        log.info(
            "waiting up to %g s for an armed vehicle on %s",
            timeout_s,
            key(VEHICLE_STATE, self.settings.zenoh.namespace),
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state = self.state()
            if state.get("link_up") and state.get("armed") and state.get("velocity"):
                position = state.get("position") or {}
                self._start = (position.get("x_m", 0.0), position.get("y_m", 0.0))
                return
            self._pause(0.1)
        raise CalibrationAbortedError(
            f"no armed vehicle with velocity reports on {key(VEHICLE_STATE)} within "
            f"{timeout_s:g} s: start `qnav bridge`, arm the car"
        )

    def _check_bounds(self) -> None:
        state = self.state()
        if not state.get("armed"):
            raise CalibrationAbortedError("the vehicle was disarmed")
        position = state.get("position")
        if self._start is not None and position:
            distance = math.hypot(
                position["x_m"] - self._start[0], position["y_m"] - self._start[1]
            )
            if distance > self.pattern.max_distance_m:
                raise CalibrationAbortedError(
                    f"{distance:.1f} m from the start, beyond max_distance_m "
                    f"{self.pattern.max_distance_m:g}"
                )

    def run_once(self, twist: Twist2D) -> dict[str, float]:
        """Command `twist` for settle + measure; the mean velocity while measured."""
        pattern = self.pattern
        start = time.monotonic()
        measure_from = start + pattern.settle_s
        end = measure_from + pattern.measure_s
        while time.monotonic() < end:
            self._check_bounds()
            self._publisher.put(encode_twist_msg(twist))
            self._pause(COMMAND_PERIOD_S)
        velocities = self._velocities(measure_from)
        if not velocities:
            raise CalibrationAbortedError("no velocity reports while measuring")
        return {
            name: sum(v[name] for v in velocities) / len(velocities)
            for name in ("forward_mps", "turn_rate_radps")
        }

    def wait_rest(self) -> None:
        """Publish nothing (the bridge's failsafe stops the car) until it is at rest."""
        deadline = time.monotonic() + self.pattern.rest_timeout_s
        rest = self.settings.failsafe.rest_speed_mps
        while time.monotonic() < deadline:
            velocity = self.state().get("velocity") or {}
            if velocity.get("speed_mps", math.inf) < rest:
                return
            self._pause(0.1)
        raise CalibrationAbortedError(f"not at rest {self.pattern.rest_timeout_s:g} s after a run")

    def calibrate(self) -> dict[str, Any]:
        """The whole pattern; the fitted scales and every run's figures."""
        output, pattern = self.settings.output, self.pattern
        speed_scale = mapping.speed_scale(output)
        turn_scale = output.turn_rate_at_full_steering_radps
        runs: list[dict[str, float]] = []
        for fraction in pattern.throttle_fractions:
            self.wait_rest()
            measured = self.run_once(Twist2D(fraction * speed_scale, 0.0))
            runs.append({"throttle": fraction, "steering": 0.0, **measured})
        turn_fractions: list[float] = []
        turn_rates: list[float] = []
        for fraction in pattern.steering_fractions:
            for side in (1.0, -1.0):  # left (counter-clockwise), then right
                self.wait_rest()
                twist = Twist2D(
                    pattern.turn_throttle_fraction * speed_scale, side * fraction * turn_scale
                )
                measured = self.run_once(twist)
                runs.append(
                    {
                        "throttle": pattern.turn_throttle_fraction,
                        "steering": side * fraction,
                        **measured,
                    }
                )
                turn_fractions.append(side * fraction)
                turn_rates.append(measured["turn_rate_radps"])
        straight = [r for r in runs if r["steering"] == 0.0]
        speed = fit_through_origin(
            [r["throttle"] for r in straight], [r["forward_mps"] for r in straight]
        )
        turn = fit_through_origin(turn_fractions, turn_rates)
        self.wait_rest()
        return {
            "speed_at_full_throttle_mps": speed,
            "turn_rate_at_full_steering_radps": turn,
            "runs": runs,
        }


def measure_scales(
    settings: BridgeSettings,
    *,
    max_distance_m: float = 15.0,
    wait_s: float = 60.0,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    """`qnav calibrate-car`: wait up to `wait_s` for an armed car behind the bridge, drive the
    pattern (aborted beyond `max_distance_m`) and fit the two scales; CalibrationAbortedError
    when the pattern was cut short (`stop` set, say by a signal, included)."""
    if settings.output.mode != "manual":
        raise ConfigError(
            "output.mode must be manual (the scales map a Twist to sticks; GUIDED takes m/s and "
            "rad/s as they are)"
        )
    calibrator = Calibrator(settings, Pattern(max_distance_m=max_distance_m), stop)
    try:
        calibrator.wait_ready(wait_s)
        return calibrator.calibrate()
    finally:
        calibrator.close()
