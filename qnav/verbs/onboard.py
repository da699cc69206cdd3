"""Handlers of the car's verbs: controller, bridge, calibrate-car, fake-vehicle, sim-car,
health. The daemons themselves live in their packages and take typed settings."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from qnav.contracts.errors import ConfigError
from qnav.contracts.health import DEFAULT_MAX_AGE_S
from qnav.options import add_print_config, config_text
from qnav.verbs.parser import (
    Verbs,
    flag,
    repeated,
    settings_options,
    verb,
    with_listing,
    world_options,
    zenoh_options,
)

if TYPE_CHECKING:
    from qnav.firmware_bridge.settings import BridgeSettings

LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"


def controller(args: argparse.Namespace) -> int:
    """`qnav controller`: the onboard daemon until SIGINT or SIGTERM."""
    from qnav.controller.config import load_config
    from qnav.controller.daemon import build, commented_config, serve

    config = load_config(args.config, args.assignments)
    if args.policy is not None:
        config = replace(config, controller=replace(config.controller, policy=str(args.policy)))
    if args.print_config:
        sys.stdout.write(commented_config(config))
        return 0
    logging.basicConfig(
        level=config.controller.log_level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    serve(build(config))
    return 0


def _bridge_settings(args: argparse.Namespace) -> BridgeSettings:
    """The bridge's settings: its --config file, then each --set."""
    from qnav.contracts.settings import parse_assignments, with_overrides
    from qnav.firmware_bridge.settings import load_settings

    settings = load_settings(args.config)
    if args.assignments:
        settings = with_overrides(settings, parse_assignments(args.assignments))
    return settings


def bridge(args: argparse.Namespace) -> int:
    """`qnav bridge`: the firmware bridge until SIGINT or SIGTERM."""
    from qnav.firmware_bridge.daemon import serve

    settings = _bridge_settings(args)
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    logging.basicConfig(level=getattr(logging, args.log_level.upper()), format=LOG_FORMAT)
    serve(settings)
    return 0


def calibrate_car(args: argparse.Namespace) -> int:
    """`qnav calibrate-car`: fit the bridge's speed and turn-rate scales on the car (and with
    --write put them into its settings file)."""
    from qnav.contracts.daemon import stop_on_signals
    from qnav.firmware_bridge.calibrate import (
        CalibrationAbortedError,
        measure_scales,
        output_section,
        write_scales,
    )

    if args.write and args.config is None:
        raise ConfigError("--write needs --config FILE: the bridge's settings file it writes to")
    settings = _bridge_settings(args)
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
    try:
        with stop_on_signals() as stop:
            result = measure_scales(
                settings, max_distance_m=args.max_distance_m, wait_s=args.wait_s, stop=stop
            )
    except CalibrationAbortedError as error:
        print(f"qnav calibrate-car: aborted: {error}", file=sys.stderr)
        return 1
    speed, turn = result["speed_at_full_throttle_mps"], result["turn_rate_at_full_steering_radps"]
    if args.write:
        write_scales(args.config, speed, turn)
        print(
            f"wrote the scales into {args.config}; restart the bridge to drive with them",
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps(result))
        return 0
    for r in result["runs"]:
        print(
            f"# throttle {r['throttle']:+.2f} steering {r['steering']:+.2f}: "
            f"{r['forward_mps']:+.3f} m/s, {r['turn_rate_radps']:+.3f} rad/s"
        )
    print(output_section(speed, turn), end="")
    return 0


def fake_vehicle(args: argparse.Namespace) -> int:
    """`qnav fake-vehicle`: the MAVLink test vehicle until SIGINT or SIGTERM."""
    from qnav.simcar.mavlink_vehicle import load_vehicle_settings, serve

    assignments = list(args.assignments)
    if args.connection:
        assignments.append(f'connection="{args.connection}"')
    if args.signing_key_file:
        assignments.append(f'signing_key_file="{args.signing_key_file}"')
    settings = load_vehicle_settings(args.config, assignments)
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    logging.basicConfig(level=getattr(logging, args.log_level.upper()), format=LOG_FORMAT)
    serve(settings, args.pose_period_s)
    return 0


def sim_car(args: argparse.Namespace) -> int:
    """`qnav sim-car`: the simulator as the car, until its episodes are done or SIGTERM."""
    from qnav.contracts.daemon import stop_on_signals
    from qnav.contracts.transport import ZenohSettings
    from qnav.options import given_settings, settings_from_args
    from qnav.sim.config import load_world
    from qnav.simcar.car import SimCar, SimCarSettings, summary, write_log

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    world = load_world(args.scenario, args.world_config, args.assignments)
    settings = settings_from_args(SimCarSettings(), args)
    if settings.firmware_connection and "start_timeout_s" not in given_settings(args):
        # An autopilot boots, finds GPS and arms in tens of seconds.
        settings = replace(settings, start_timeout_s=180.0)
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    zenoh = ZenohSettings(
        listen=tuple(args.listen or ()),
        connect=tuple(args.connect or ()),
        namespace=args.namespace or "",
    )
    car = SimCar(world, settings, zenoh)

    def report(entry: Any) -> None:
        print(f"episode {entry.episode}: {entry.outcome}, {entry.steps} steps", flush=True)

    with stop_on_signals() as stop:
        episodes = car.run(stop, progress=report)
    if args.log:
        write_log(episodes, args.log)
    print(json.dumps(summary(episodes)), flush=True)
    return 0


def health(args: argparse.Namespace) -> int:
    """`qnav health`: 0 while the daemon's loop beats (a container HEALTHCHECK), 1 otherwise."""
    import sys

    from qnav.contracts.health import HEALTH_FILE_ENV, check_health, health_path

    path = args.file or health_path()
    if path is None:
        print(f"qnav health: give --file or set {HEALTH_FILE_ENV}", file=sys.stderr)
        return 2
    healthy, explanation = check_health(path, args.max_age_s)
    print(f"{'healthy' if healthy else 'unhealthy'}: {explanation}")
    return 0 if healthy else 1


def add_verbs(verbs: Verbs) -> None:
    """`qnav controller`, `sim-car`, `health`, `bridge`, `calibrate-car` and `fake-vehicle`:
    their options."""
    _add_controller(verbs)
    _add_sim_car(verbs)
    _add_health(verbs)
    _add_bridge(verbs)
    _add_calibrate_car(verbs)
    _add_fake_vehicle(verbs)


def _add_controller(verbs: Verbs) -> None:
    """`qnav controller`: the onboard daemon."""
    parser = verb(
        verbs,
        controller,
        "controller",
        help="the onboard daemon: scans, poses, targets in over zenoh, motor commands out",
    )
    with_listing(
        parser,
        "qnav.controller.config:DaemonConfig",
        "settings (--set SECTION.FIELD=VALUE, or in the --config file; defaults below)",
    )
    parser.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML settings (config/controller.toml)"
    )
    parser.add_argument(
        "--policy", type=Path, metavar="FILE.onnx", help="policy file (over controller.policy)"
    )
    repeated(
        parser,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one setting, e.g. --set controller.trigger=scan (repeatable)",
    )
    add_print_config(parser)


def _add_sim_car(verbs: Verbs) -> None:
    """`qnav sim-car`: the simulator as the car."""
    parser = verb(
        verbs,
        sim_car,
        "sim-car",
        help="the simulator as the car: scans and poses out on zenoh, motion in over MAVLink",
    )
    world_options(parser, "walls-increment")
    settings_options(parser, "qnav.simcar.car:SimCarSettings", "sim-car settings")
    add_print_config(parser)
    parser.add_argument("--log", type=Path, help="write the episodes as JSON lines here")
    zenoh_options(parser)


def _add_health(verbs: Verbs) -> None:
    """`qnav health`: the image's HEALTHCHECK."""
    parser = verb(
        verbs,
        health,
        "health",
        help="exit 0 while a daemon's loop beats (its QNAV_HEALTH_FILE is fresh): the image's "
        "HEALTHCHECK",
    )
    parser.add_argument(
        "--file", type=Path, metavar="PATH", help="health file (default: $QNAV_HEALTH_FILE)"
    )
    parser.add_argument(
        "--max-age-s",
        type=float,
        default=DEFAULT_MAX_AGE_S,
        help=f"oldest acceptable beat in seconds ({DEFAULT_MAX_AGE_S:g})",
    )


def _add_bridge(verbs: Verbs) -> None:
    """`qnav bridge`: zenoh to MAVLink."""
    parser = verb(
        verbs,
        bridge,
        "bridge",
        help="the firmware bridge: commands from zenoh to the car over MAVLink",
    )
    with_listing(
        parser,
        "qnav.firmware_bridge.settings:BridgeSettings",
        "settings (--set SECTION.FIELD=VALUE, or in the --config file; defaults below)",
    )
    parser.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML settings (see config/bridge.toml)"
    )
    repeated(
        parser,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one setting, e.g. --set mavlink.connection=udpin:0.0.0.0:14550",
    )
    add_print_config(parser)
    parser.add_argument(
        "--log-level", default="info", choices=["debug", "info", "warning"], help="(info)"
    )


def _add_calibrate_car(verbs: Verbs) -> None:
    """`qnav calibrate-car`: a bounded pattern through a running bridge."""
    parser = verb(
        verbs,
        calibrate_car,
        "calibrate-car",
        help="drive a short bounded pattern through a running bridge and fit its speed and "
        "turn-rate scales from the vehicle's own velocity (the car must be armed, and watched)",
    )
    parser.add_argument(
        "--config", type=Path, metavar="FILE", help="the bridge's TOML settings (its zenoh)"
    )
    repeated(
        parser,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one bridge setting (as `qnav bridge --set`)",
    )
    parser.add_argument(
        "--max-distance-m", type=float, default=15.0, help="abort beyond this (15 m)"
    )
    parser.add_argument(
        "--wait-s", type=float, default=60.0, help="wait this long for an armed car (60 s)"
    )
    flag(parser, "--json", "print one JSON object")
    flag(
        parser,
        "--write",
        "write the measured scales into the --config file's [output] section (restart the "
        "bridge to drive with them; until then it assumes a fast car)",
    )


def _add_fake_vehicle(verbs: Verbs) -> None:
    """`qnav fake-vehicle`: a MAVLink car for tests."""
    parser = verb(
        verbs,
        fake_vehicle,
        "fake-vehicle",
        help="a small MAVLink car that behaves like ArduPilot Rover",
    )
    with_listing(
        parser,
        "qnav.simcar.mavlink_vehicle:MavlinkVehicleSettings",
        "settings (--set FIELD=VALUE, or in the --config file; defaults below)",
    )
    parser.add_argument("--config", type=Path, metavar="FILE", help="TOML file of vehicle settings")
    parser.add_argument(
        "--connection",
        help="MAVLink connection string (default udpout:127.0.0.1:14550, to the bridge)",
    )
    parser.add_argument(
        "--signing-key-file", metavar="FILE", help="sign, and accept only signed messages"
    )
    repeated(
        parser,
        "--set",
        "assignments",
        "FIELD=VALUE",
        "change one setting, e.g. --set dynamics.max_speed_mps=1.0 (repeatable)",
    )
    parser.add_argument(
        "--pose-period-s", type=float, default=1.0, help="log the pose this often (0: never)"
    )
    add_print_config(parser)
    parser.add_argument(
        "--log-level", default="info", choices=["debug", "info", "warning"], help="(info)"
    )
