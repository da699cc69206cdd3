"""Policies delivered by `qnav serve` to the controller daemon, over real loopback zenoh sessions
with scouting off and real ONNX files through onnxruntime.

The daemon runs in a thread of this process (`controller.daemon.build(config).run()`, as
`qnav controller` runs it); the server is `qnav.serve.run` in another thread, or, where the test is
about a server that misbehaves, a zenoh session of the test that announces and answers as told.
The car's sensors are a third session publishing a scan, a pose and a target every 50 ms.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from qnav.contracts import delivery, wire
from qnav.contracts.daemon import stop_process
from qnav.contracts.policy_file import PolicyContract
from qnav.contracts.transport import ZenohSettings, open_session
from qnav.controller.config import (
    ControllerSettings,
    DaemonConfig,
    PolicySourceSettings,
    SafetySettings,
)
from qnav.controller.daemon import Daemon, build
from qnav.controller.decision import Controller, Input
from qnav.controller.onnx_file import read_onnx
from qnav.controller.policy import PolicyRuntime
from qnav.controller.recording import RecorderSettings, read_recordings, record
from qnav.serve import ServeSettings
from qnav.serve import run as run_server
from tests.conftest import PolicyFactory
from tests.controller.test_daemon import LOOKAHEAD_OFF, Listener

FAR = (8.0, 8.0)
"""A target the car drives to (it never gets there: the pose is fixed)."""
HERE = (1.0, 1.0)
"""The car's fixed pose: a target here is reached at once."""
AT_REST = ("no_target", "target_reached", "estop_latched")


def contract_of(path: Path) -> PolicyContract:
    return PolicyContract.from_metadata(read_onnx(path).metadata, str(path))


class Sensors:
    """The car's scan, pose and target, published every 50 ms; `target` can be moved."""

    def __init__(self, endpoint: str, beams: int) -> None:
        self.target = FAR
        self.session = open_session(ZenohSettings(connect=(endpoint,)))
        # Nothing nearer than 1 m: clear of the proximity stop's default field (1 m ahead).
        ranges = np.random.default_rng(0).uniform(1.0, 8.0, beams).astype(np.float32)
        self.scan = wire.Scan(0.0, "laser", -math.pi, 2 * math.pi / beams, 0.1, 30.0, ranges)
        self.pose = wire.Pose2D(0.0, "map", *HERE, 0.3)
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._publish, daemon=True)
        self.thread.start()

    def payloads(self) -> dict[Input, bytes]:
        return {
            Input.SCAN: wire.encode_scan_msg(self.scan),
            Input.POSE: wire.encode_pose_msg(self.pose),
            Input.TARGET: wire.encode_pose_msg(wire.Pose2D(0.0, "map", *self.target)),
        }

    def _publish(self) -> None:
        keys = {Input.SCAN: wire.SCAN, Input.POSE: wire.POSE, Input.TARGET: wire.TARGET_POSE}
        while not self.done.wait(0.05):
            for source, payload in self.payloads().items():
                self.session.put(wire.key(keys[source]), payload)

    def close(self) -> None:
        self.done.set()
        self.thread.join()
        self.session.close()


def expected_q(policy: Path, sensors: Sensors) -> list[float]:
    """The Q values the controller gives on the sensors' constant inputs with `policy` (every
    decision of an episode alike: the window holds copies of one frame)."""
    controller = Controller(PolicyRuntime(policy), SafetySettings(frame_id="map"))
    for source, payload in sensors.payloads().items():
        assert controller.receive(source, payload, 0.0) is None
    status = controller.decide(0.0).status
    assert status.q_values is not None
    return list(status.q_values)


class Car:
    """The daemon (in a thread), its sensors and a listener of its status."""

    def __init__(self, endpoint: str, config: DaemonConfig, beams: int) -> None:
        self.daemon: Daemon = build(config)
        self.thread = threading.Thread(target=self.daemon.run, daemon=True)
        self.thread.start()
        self.listener = Listener(endpoint)
        self.sensors = Sensors(endpoint, beams)

    def close(self) -> None:
        self.daemon.request_stop()
        self.thread.join(timeout=30)
        assert not self.thread.is_alive(), "the daemon did not stop"
        self.sensors.close()
        self.listener.session.close()

    def statuses(self, since: int = 0) -> list[dict[str, Any]]:
        with self.listener.lock:
            return list(self.listener.statuses[since:])

    def come_to_rest(self) -> dict[str, Any]:
        """Put the target where the car is and wait for it to report it reached: the car is at
        rest, where a verified policy comes in at once. That status."""
        self.sensors.target = HERE
        return self.listener.wait_for(lambda s: s["reason"] == "target_reached", timeout=30)


@pytest.fixture
def policies(make_policy: PolicyFactory) -> tuple[Path, Path]:
    """(old, new): two policies for the same car, with different weights."""
    return make_policy(seed=0), make_policy(seed=1)


@pytest.fixture
def keys(tmp_path: Path) -> tuple[Path, Path]:
    """(private, public) key files."""
    private, public = delivery.generate_key_pair()
    (tmp_path / "keys").mkdir()
    paths = tmp_path / "keys" / "policy.key", tmp_path / "keys" / "policy.pub"
    paths[0].write_bytes(private)
    paths[1].write_bytes(public)
    return paths


def car_zenoh(car: Car) -> ZenohSettings:
    """Settings of a session that joins the car's zenoh hub."""
    return ZenohSettings(connect=car.daemon.config.zenoh.listen)


def car_config(
    local: Path, endpoint: str, public_key: Path, tmp_path: Path, **policy: Any
) -> DaemonConfig:
    settings = {"chunk_timeout_s": 1.0, "retry_interval_s": 60.0} | policy
    return DaemonConfig(
        controller=ControllerSettings(policy=str(local)),
        safety=SafetySettings(frame_id="map"),
        policy=PolicySourceSettings(
            source="server",
            public_key=str(public_key),
            cache_dir=str(tmp_path / "cache"),
            **settings,
        ),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=LOOKAHEAD_OFF,
    )


@pytest.fixture
def start_car(
    tmp_path: Path, endpoint: str, keys: tuple[Path, Path]
) -> Iterator[Callable[..., Car]]:
    cars: list[Car] = []

    def start(local: Path, **policy: Any) -> Car:
        config = car_config(local, endpoint, keys[1], tmp_path, **policy)
        car = Car(endpoint, config, contract_of(local).num_beams)
        cars.append(car)
        return car

    yield start
    for car in cars:
        car.close()


@pytest.fixture
def start_server(endpoint: str) -> Iterator[Callable[..., None]]:
    """`qnav serve`'s loop in a thread, connected to the car's endpoint."""
    stops: list[tuple[threading.Event, threading.Thread]] = []

    def start(sources: tuple[Path, ...], private_key: Path, chunk_bytes: int = 16384) -> None:
        settings = ServeSettings(
            sources=sources,
            private_key=private_key,
            zenoh=ZenohSettings(connect=(endpoint,)),
            poll_s=0.1,
            announce_interval_s=0.3,
            chunk_bytes=chunk_bytes,
        )
        stop = threading.Event()
        thread = threading.Thread(target=run_server, args=(settings, stop), daemon=True)
        thread.start()
        stops.append((stop, thread))

    yield start
    for stop, thread in stops:
        stop.set()
        thread.join(timeout=30)


def test_a_delivered_policy_is_swapped_in_at_the_next_stop_and_decides_from_then_on(
    tmp_path: Path,
    policies: tuple[Path, Path],
    keys: tuple[Path, Path],
    start_car: Callable[..., Car],
    start_server: Callable[..., None],
) -> None:
    old, new = policies
    served = tmp_path / "served"
    served.mkdir()
    car = start_car(old)
    start_server((served,), keys[0])
    listener = car.listener
    stop_recording = threading.Event()
    recorder = threading.Thread(
        target=record,
        args=(RecorderSettings(zenoh=car_zenoh(car)), stop_recording, tmp_path / "rec"),
        daemon=True,
    )
    recorder.start()
    old_q, new_q = expected_q(old, car.sensors), expected_q(new, car.sensors)
    assert not np.allclose(old_q, new_q, atol=1e-4)
    old_version = delivery.version_of_file(old)

    driving = listener.wait_for(lambda s: s["reason"] == "policy", timeout=30)
    assert driving["policy_version"] == old_version
    assert np.allclose(driving["q_values"], old_q, atol=1e-5)

    # A better policy appears on the desktop while the car drives: it is fetched and verified,
    # but waits for the car to stop.
    shutil.copy(new, served / "policy.onnx")
    pending = listener.wait_for(lambda s: s["delivery"]["pending"] is not None, timeout=30)
    new_version = pending["delivery"]["pending"]
    assert new_version == delivery.version_of("served-policy", delivery.sha256_of(new.read_bytes()))
    mark = listener.mark()
    listener.wait_for(lambda s: s["reason"] == "policy", since=mark + 5)
    for status in car.statuses(mark):
        assert status["reason"] == "policy" and status["policy_version"] == old_version
        assert np.allclose(status["q_values"], old_q, atol=1e-5)

    # The car reaches its target: the new policy comes in while it is stopped ...
    car.sensors.target = HERE
    swapped = listener.wait_for(lambda s: s["policy_version"] == new_version, since=mark)
    assert swapped["reason"] in AT_REST
    assert swapped["counters"]["policy_swaps"] == 1 and swapped["delivery"]["swaps"] == 1
    assert swapped["delivery"]["pending"] is None
    for status in car.statuses(mark):
        if status["reason"] == "policy":
            assert status["policy_version"] == old_version

    # ... and decides the next episode.
    car.sensors.target = FAR
    after = listener.wait_for(lambda s: s["reason"] == "policy")
    assert after["policy_version"] == new_version
    assert np.allclose(after["q_values"], new_q, atol=1e-5)
    assert (tmp_path / "cache" / f"{new_version}.onnx").read_bytes() == new.read_bytes()

    # The recording holds the announcement and, in every status, the version that drove.
    listener.wait_for(lambda s: s["reason"] == "policy", since=listener.mark() + 3)
    stop_recording.set()
    recorder.join(timeout=30)
    messages = list(read_recordings(sorted((tmp_path / "rec").glob("*.mcap"))))
    announced = [
        delivery.decode_announcement(m.payload).version
        for m in messages
        if m.topic == "/" + wire.POLICY_ANNOUNCEMENT.name
    ]
    assert new_version in announced
    recorded = [
        wire.decode_json_msg(m.payload)
        for m in messages
        if m.topic == "/" + wire.CONTROLLER_STATUS.name
    ]
    versions = [status["policy_version"] for status in recorded]
    assert versions[0] == old_version and versions[-1] == new_version
    drove = {status["policy_version"] for status in recorded if status["reason"] == "policy"}
    assert drove == {old_version, new_version}


def test_a_car_with_no_server_reachable_drives_on_its_local_file_and_takes_a_late_servers_policy(
    tmp_path: Path,
    policies: tuple[Path, Path],
    keys: tuple[Path, Path],
    start_car: Callable[..., Car],
    start_server: Callable[..., None],
) -> None:
    old, new = policies
    car = start_car(old)
    listener = car.listener
    at_rest = car.come_to_rest()
    assert at_rest["policy_version"] == delivery.version_of_file(old)
    assert at_rest["delivery"]["announced"] is None
    car.sensors.target = FAR
    driving = listener.wait_for(lambda s: s["reason"] == "policy")
    assert driving["policy_version"] == delivery.version_of_file(old)

    car.sensors.target = HERE
    start_server((new,), keys[0])
    swapped = listener.wait_for(
        lambda s: s["policy_version"] != delivery.version_of_file(old), timeout=30
    )
    assert swapped["policy_version"] == delivery.version_of_file(new)
    assert swapped["reason"] == "target_reached"


class BadServer:
    """A server that misbehaves as told: it announces `announcement` and answers chunk queries
    with `answer(index, chunk)` (None: no answer at all)."""

    def __init__(
        self,
        endpoint: str,
        announcement: bytes,
        data: bytes,
        chunk_bytes: int,
        answer: Callable[[int, bytes], bytes | None],
    ) -> None:
        self.session = open_session(ZenohSettings(connect=(endpoint,)))
        self.queries = 0
        self.lock = threading.Lock()

        def on_query(query: Any) -> None:
            parsed = delivery.parse_chunk_key(str(query.key_expr))
            if parsed is None:
                return
            with self.lock:
                self.queries += 1
            index = parsed[1]
            payload = answer(index, data[index * chunk_bytes : (index + 1) * chunk_bytes])
            if payload is not None:
                query.reply(query.key_expr, payload)

        self.queryable = self.session.declare_queryable(f"{delivery.POLICY_FILE}/**", on_query)
        self.done = threading.Event()

        def announce() -> None:
            while not self.done.wait(0.3):
                self.session.put(wire.key(wire.POLICY_ANNOUNCEMENT), announcement)

        self.thread = threading.Thread(target=announce, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.done.set()
        self.thread.join()
        self.queryable.undeclare()
        self.session.close()


def signed(path: Path, private_key: Path, chunk_bytes: int = 16384) -> delivery.Announcement:
    key = delivery.load_private_key(private_key, "test key")
    return delivery.make_announcement(
        path.read_bytes(), path.stem, contract_of(path), key, chunk_bytes
    )


def refused_and_old_still_drives(car: Car, old: Path, match: str) -> dict[str, Any]:
    """Wait for a refusal matching `match`; check the old policy decides the next episode."""
    listener = car.listener
    refusal = listener.wait_for(
        lambda s: match in (s["delivery"]["last_refusal"] or ""), timeout=30
    )
    assert refusal["delivery"]["pending"] is None
    car.sensors.target = FAR
    driving = listener.wait_for(lambda s: s["reason"] == "policy")
    assert driving["policy_version"] == delivery.version_of_file(old)
    assert np.allclose(driving["q_values"], expected_q(old, car.sensors), atol=1e-5)
    for status in car.statuses():
        assert status["policy_version"] == delivery.version_of_file(old)
        assert status["counters"]["policy_swaps"] == 0
    return refusal


@pytest.mark.parametrize("fault", ["tampered", "wrong_signature", "cut_halfway"])
def test_a_bad_delivery_is_refused_with_the_old_policy_still_driving(  # noqa: PLR0917
    fault: str,
    tmp_path: Path,
    endpoint: str,
    policies: tuple[Path, Path],
    keys: tuple[Path, Path],
    start_car: Callable[..., Car],
) -> None:
    old, new = policies
    car = start_car(old)
    car.come_to_rest()  # at rest all along: a policy that passed would come in at once
    data = new.read_bytes()
    chunks = math.ceil(len(data) / 16384)
    assert chunks >= 4
    private = keys[0]
    if fault == "wrong_signature":
        other = tmp_path / "other.key"
        other.write_bytes(delivery.generate_key_pair()[0])
        private = other
    announcement = delivery.encode_announcement(signed(new, private))

    def answer(index: int, chunk: bytes) -> bytes | None:
        if fault == "tampered" and index == 1:
            return bytes([chunk[0] ^ 0xFF]) + chunk[1:]
        if fault == "cut_halfway" and index >= chunks // 2:
            return None
        return chunk

    server = BadServer(endpoint, announcement, data, 16384, answer)
    try:
        match = {
            "tampered": "sha256",
            "wrong_signature": "signature does not verify with policy.public_key",
            "cut_halfway": f"transfer cut at chunk {chunks // 2 + 1} of {chunks}",
        }[fault]
        refused_and_old_still_drives(car, old, match)
        if fault == "wrong_signature":
            assert server.queries == 0  # refused before a byte was fetched
    finally:
        server.close()


def test_an_incompatible_contract_is_refused_unfetched_with_the_old_policy_still_driving(
    tmp_path: Path,
    make_policy: PolicyFactory,
    keys: tuple[Path, Path],
    start_car: Callable[..., Car],
    start_server: Callable[..., None],
) -> None:
    old, other_car = make_policy(seed=0), make_policy("walls-increment", seed=1)
    assert contract_of(other_car).dynamics != contract_of(old).dynamics
    car = start_car(old)
    car.come_to_rest()
    start_server((other_car,), keys[0])
    refusal = refused_and_old_still_drives(car, old, "this car runs")
    assert "contract" in refusal["delivery"]["last_refusal"]
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").iterdir())


def test_a_slow_or_garbage_server_never_stops_the_car_running_its_policy(
    endpoint: str,
    policies: tuple[Path, Path],
    keys: tuple[Path, Path],
    start_car: Callable[..., Car],
) -> None:
    old, new = policies
    car = start_car(old, chunk_timeout_s=0.5, retry_interval_s=0.0)
    listener = car.listener
    listener.wait_for(lambda s: s["reason"] == "policy", timeout=30)
    mark = listener.mark()

    # Garbage on the announcement key: counted, nothing else.
    for payload in (
        b"garbage",
        wire.encode_json_msg({"format": delivery.ANNOUNCEMENT_FORMAT, "version": "x"}),
        wire.encode_json_msg({"format": "other"}),
    ):
        listener.put(wire.POLICY_ANNOUNCEMENT, payload)
    listener.wait_for(lambda s: s["delivery"]["malformed"] >= 3, since=mark)

    # A server that answers each chunk after the car stopped waiting, then garbage chunks.
    data = new.read_bytes()
    slow = BadServer(
        endpoint,
        delivery.encode_announcement(signed(new, keys[0])),
        data,
        16384,
        lambda index, chunk: time.sleep(1.0) or chunk,  # type: ignore[func-returns-value]
    )
    try:
        listener.wait_for(lambda s: "no answer within" in (s["delivery"]["last_refusal"] or ""))
    finally:
        slow.close()
    garbage = BadServer(
        endpoint,
        delivery.encode_announcement(signed(new, keys[0], chunk_bytes=20000)),
        data,
        20000,
        lambda index, chunk: b"\x00" * 7,
    )
    try:
        listener.wait_for(
            lambda s: "7 bytes, expected 20000" in (s["delivery"]["last_refusal"] or "")
        )
    finally:
        garbage.close()
    # The car decided all along, and still does.
    listener.wait_for(lambda s: s["reason"] == "policy", since=listener.mark() + 3)
    seen = car.statuses(mark)
    for status in seen:
        assert status["reason"] == "policy", status["reason"]
        assert status["policy_version"] == delivery.version_of_file(old)
    assert car.thread.is_alive()


def test_qnav_controller_takes_the_policy_qnav_serve_announces_with_keys_from_qnav_keys(
    tmp_path: Path,
    endpoint: str,
    policies: tuple[Path, Path],
    processes: list[subprocess.Popen[Any]],
) -> None:
    """The commands as a user runs them, each its own process; settings paths relative to the
    settings file."""
    from tests.controller.test_daemon import QNAV, ROOT, start_daemon

    old, new = policies
    made = subprocess.run(
        [QNAV, "keys", str(tmp_path / "keys")], capture_output=True, text=True, check=False
    )
    assert made.returncode == 0, made.stderr
    config = DaemonConfig(
        controller=ControllerSettings(policy=str(old)),
        safety=SafetySettings(frame_id="map"),
        policy=PolicySourceSettings(
            source="server", public_key="keys/policy-signing.pub", cache_dir="cache"
        ),
        zenoh=ZenohSettings(listen=(endpoint,), connect=()),
        lookahead=LOOKAHEAD_OFF,
    )
    daemon = start_daemon(tmp_path, config, processes)
    server = subprocess.Popen(
        [QNAV, "serve", str(new), "--key", str(tmp_path / "keys" / "policy-signing.key"),
         "--connect", endpoint, "--poll-s", "0.2", "--announce-interval-s", "0.3"],
        cwd=ROOT, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    listener = Listener(endpoint)
    sensors = Sensors(endpoint, contract_of(old).num_beams)
    sensors.target = HERE
    try:
        swapped = listener.wait_for(
            lambda s: s["policy_version"] == delivery.version_of_file(new), timeout=60
        )
        assert swapped["reason"] == "target_reached"
        assert (tmp_path / "cache" / f"{swapped['policy_version']}.onnx").is_file()
        sensors.target = FAR
        driving = listener.wait_for(lambda s: s["reason"] == "policy")
        assert np.allclose(driving["q_values"], expected_q(new, sensors), atol=1e-5)
    finally:
        sensors.close()
        listener.session.close()
        for process in (server, daemon):
            stop_process(process, timeout_s=30.0)
    assert daemon.returncode == 0 and server.returncode == 0
