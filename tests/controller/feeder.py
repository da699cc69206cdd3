"""The car's sensors in a separate process, for the daemon tests.

    python -m tests.controller.feeder ENDPOINT [--namespace NS] [--beams B] [--target pose|point]

Publishes a target twice a second and a pose (and a B-reading LaserScan over [-pi, pi) unless
B is 0) at --rate, until stdin closes. Lines on stdin switch streams: `scan off`, `scan on`,
`pose off`, `pose on`; and what the scans read: `ranges random` (1 to 8 m, the start),
`ranges wall` (a wall 0.1 m ahead of the car), `ranges neginf` (every reading -inf). Prints
`ready` once its session is open.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time

import numpy as np

from qnav.contracts import wire
from qnav.contracts.transport import ZenohSettings, open_session


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("endpoint")
    parser.add_argument("--namespace", default="")
    parser.add_argument("--beams", type=int, default=720)
    parser.add_argument("--rate", type=float, default=20.0)
    parser.add_argument("--target", choices=["pose", "point"], default="pose")
    parser.add_argument("--frame", default="map")
    args = parser.parse_args()

    enabled = {"scan": args.beams > 0, "pose": True}
    # Nothing nearer than 1 m: clear of the proximity stop's default field (1 m ahead).
    random = np.random.default_rng(0).uniform(1.0, 8.0, args.beams).astype(np.float32)
    bearing = -math.pi + 2 * math.pi / max(args.beams, 1) * np.arange(args.beams)
    ahead = np.abs(bearing) < 1.0  # the lidar's x axis is the car's heading
    wall = np.where(ahead, 0.1 / np.cos(bearing), random).astype(np.float32)
    shapes = {"random": random, "wall": wall, "neginf": np.full(args.beams, -np.inf, np.float32)}
    ranges = [random]
    done = threading.Event()

    def read_commands() -> None:
        for line in sys.stdin:
            parts = line.split()
            if len(parts) == 2 and parts[0] in enabled:
                enabled[parts[0]] = parts[1] == "on"
            elif len(parts) == 2 and parts[0] == "ranges" and parts[1] in shapes:
                ranges[0] = shapes[parts[1]]
        done.set()

    threading.Thread(target=read_commands, daemon=True).start()
    ns = args.namespace
    with open_session(ZenohSettings(connect=(args.endpoint,))) as session:
        scan_pub = session.declare_publisher(wire.key(wire.SCAN, ns))
        pose_pub = session.declare_publisher(wire.key(wire.POSE, ns))
        if args.target == "pose":
            target_pub = session.declare_publisher(wire.key(wire.TARGET_POSE, ns))
            target = wire.encode_pose_msg(wire.Pose2D(0.0, args.frame, 8.0, 8.0))
        else:
            target_pub = session.declare_publisher(wire.key(wire.TARGET_POINT, ns))
            target = wire.encode_point_msg(wire.Pose2D(0.0, args.frame, 8.0, 8.0))
        print("ready", flush=True)
        period = 1.0 / args.rate
        step = 0
        while not done.wait(period):
            now = time.monotonic()
            if step % max(1, round(args.rate / 2)) == 0:
                target_pub.put(target)
            if enabled["pose"]:
                pose_pub.put(wire.encode_pose_msg(wire.Pose2D(now, args.frame, 1.0, 1.0, 0.3)))
            if enabled["scan"]:
                scan = wire.Scan(
                    now, "laser", -math.pi, 2 * math.pi / args.beams, 0.1, 30.0, ranges[0]
                )
                scan_pub.put(wire.encode_scan_msg(scan))
            step += 1


if __name__ == "__main__":
    main()
