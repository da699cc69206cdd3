"""The car's side of policy delivery: take the policies `qnav serve` announces, safely.

`PolicyFetcher` listens to announcements (`contracts.delivery`) and works in a thread of its
own, never in the decision loop: for a version the car does not run, it checks the signature
with the car's public key, the announced contract against the running policy's
(`contracts.delivery.contract_mismatch`), fetches the file chunk by chunk with a timeout on
each, checks its size and sha256, loads it (the file's own contract is checked again) and runs
it once on a built-in input. Only then is it offered (`Candidate`) to the daemon, which swaps it
in between two decisions while the car is stopped (`controller.decision.Controller.at_rest`).

Every failure leaves the running policy alone and is reported in the status (`delivery`): a
signature, a contract or a file that fails is refused for good (the same announcement is not
fetched again); a transfer that fails (no server, a slow one, one cut off halfway) or a file
whose hash is wrong is tried again at the next announcement after `policy.retry_interval_s`.
A malformed announcement is counted and logged (rate-limited), nothing more.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from qnav.contracts import delivery
from qnav.contracts.errors import PolicyFileError
from qnav.contracts.policy_file import PolicyContract
from qnav.contracts.wire import WireError
from qnav.controller.config import PolicySourceSettings
from qnav.controller.policy import Backend, PolicyRuntime

log = logging.getLogger("qnav.controller.delivery")


STOP_WAIT_S = 0.2
"""How long shutdown waits for the fetching thread (a daemon thread: it dies with the process)."""


class Candidate(NamedTuple):
    """A verified, loaded, tried policy waiting for the car to stop."""

    runtime: PolicyRuntime
    """The loaded policy."""
    version: str
    """Its version."""
    sha256: str
    """Its file's hash."""


class TransferError(Exception):
    """A transfer failed (no answer, an error answer, a chunk of the wrong size)."""


@dataclass
class DeliveryStatus:
    """What the status message reports about delivery (`delivery`)."""

    source: str = "server"
    """Where policies come from."""
    announced: str | None = None
    """The version last announced by a server (None: none heard)."""
    pending: str | None = None
    """A verified version waiting for the car to stop, to be swapped in."""
    fetching: str | None = None
    """The version being fetched now."""
    swaps: int = 0
    """Policies swapped in."""
    refusals: int = 0
    """Announced versions refused or failed (each attempt counted)."""
    malformed: int = 0
    """Announcements that were not well-formed."""
    last_refusal: str | None = None
    """Why the last refusal happened."""
    refused: dict[str, str] = field(default_factory=dict)
    """Refused for good: the announcement's sha256 -> why (never fetched again)."""

    def to_dict(self) -> dict[str, Any]:
        """As plain JSON values."""
        return {
            "source": self.source,
            "announced": self.announced,
            "pending": self.pending,
            "fetching": self.fetching,
            "swaps": self.swaps,
            "refusals": self.refusals,
            "malformed": self.malformed,
            "last_refusal": self.last_refusal,
        }


def probe(runtime: PolicyRuntime) -> None:
    """Run a policy once on a built-in input (open space, the target 1 m ahead) and restart it;
    `PolicyFileError` if it does not answer with finite Q values."""
    beams = runtime.contract.num_beams
    scan = np.full(beams, runtime.contract.max_range_m, dtype=np.float32) if beams else None
    try:
        decision = runtime.step(scan, np.array([1.0, 0.0, 1.0]))
    except Exception as error:  # whatever a bad file does, it is only ever refused
        raise PolicyFileError(f"the policy failed its trial run: {error}") from None
    finally:
        runtime.reset()
    if decision.q_values.shape != (3,) or not np.all(np.isfinite(decision.q_values)):
        raise PolicyFileError(f"the policy's trial run gave Q values {decision.q_values.tolist()}")


class PolicyFetcher:
    """Announcements in (zenoh's thread), verified candidates out (`offer`, its own thread)."""

    def __init__(
        self,
        settings: PolicySourceSettings,
        *,
        public_key: Any,
        cache_dir: Path,
        backend: Backend,
        running: Callable[[], tuple[PolicyContract, str]],
        offer: Callable[[Candidate], None],
        warn: Callable[[str, str], object],
    ) -> None:
        """`running()` gives the running policy's contract and sha256 (and of a pending one,
        if the daemon prefers); `offer` takes a candidate; `warn(kind, message)` logs,
        rate-limited by kind."""
        self.settings = settings
        self.public_key = public_key
        self.cache_dir = cache_dir
        self.backend = backend
        self.running = running
        self.offer = offer
        self.warn = warn
        self.status = DeliveryStatus()
        self.lock = threading.Lock()
        """Guards `status` and the mailbox."""
        self._mailbox: delivery.Announcement | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._failed_at: dict[str, float] = {}
        self._session: Any = None
        self._namespace = ""
        self._thread: threading.Thread | None = None

    # ---- zenoh's side ---------------------------------------------------------------------

    def on_payload(self, payload: bytes) -> None:
        """Take one announcement payload (from zenoh's thread): never blocks, never raises."""
        try:
            announcement = delivery.decode_announcement(payload)
        except Exception as error:  # a malformed announcement is counted, nothing more
            why = str(error) if isinstance(error, WireError) else f"{type(error).__name__}: {error}"
            with self.lock:
                self.status.malformed += 1
            self.warn("announcement", f"malformed policy announcement refused: {why}")
            return
        with self.lock:
            self.status.announced = announcement.version
            self._mailbox = announcement
        self._wake.set()

    # ---- the fetching thread --------------------------------------------------------------

    def start(self, session: Any, namespace: str) -> None:
        """Start fetching through `session`."""
        self._session, self._namespace = session, namespace
        self._thread = threading.Thread(target=self._work, name="policy-fetch", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to stop (a transfer in progress ends at its next chunk). Waits a
        moment only: the daemon's shutdown must not wait for a slow server."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=STOP_WAIT_S)

    def _work(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            with self.lock:
                announcement, self._mailbox = self._mailbox, None
            if announcement is not None and not self._stop.is_set():
                self.consider(announcement)

    def consider(self, announcement: delivery.Announcement) -> Candidate | None:
        """Verify, fetch, check and try one announced policy; offer it if all passes."""
        contract, running_sha = self.running()
        with self.lock:
            if announcement.sha256 == running_sha or announcement.version == self.status.pending:
                return None
            if announcement.sha256 in self.status.refused:
                return None
        failed = self._failed_at.get(announcement.sha256)
        if failed is not None and time.monotonic() - failed < self.settings.retry_interval_s:
            return None
        version = announcement.version
        why = self._refusal(announcement, contract)
        if why is not None:
            self._refuse(announcement, why, for_good=True)
            return None
        with self.lock:
            self.status.fetching = version
        try:
            candidate = self._obtain(announcement, contract)
        finally:
            with self.lock:
                self.status.fetching = None
        if candidate is None:
            return None
        log.info("policy %s verified and tried; it is swapped in at the next stop", version)
        with self.lock:
            self.status.pending = version
        self.offer(candidate)
        return candidate

    def _obtain(
        self, announcement: delivery.Announcement, contract: PolicyContract
    ) -> Candidate | None:
        """Fetch, hash-check, load and try (`status.fetching` is set meanwhile)."""
        version = announcement.version
        try:
            data = self.fetch(announcement)
        except TransferError as error:
            self._refuse(announcement, str(error), for_good=False)
            return None
        found = delivery.sha256_of(data)
        if found != announcement.sha256:
            self._refuse(
                announcement,
                f"{version}: the received file's sha256 is {found[:16]}..., the announcement's "
                f"{announcement.sha256[:16]}... (a tampered or corrupted file)",
                for_good=False,
            )
            return None
        try:
            return self._load(announcement, data, contract)
        except PolicyFileError as error:
            self._refuse(announcement, f"{version}: {error}", for_good=True)
        except OSError as error:  # a full disk, a cache folder removed at shutdown
            self._refuse(announcement, f"{version}: cannot write it to policy.cache_dir: {error}",
                         for_good=False)  # fmt: skip
        return None

    def _refusal(self, announcement: delivery.Announcement, contract: PolicyContract) -> str | None:
        version = announcement.version
        if not delivery.verify(self.public_key, announcement):
            return f"{version}: its signature does not verify with policy.public_key"
        if announcement.size_bytes > self.settings.max_file_bytes:
            return (
                f"{version}: {announcement.size_bytes} bytes is more than "
                f"policy.max_file_bytes = {self.settings.max_file_bytes}"
            )
        mismatch = delivery.contract_mismatch(contract, announcement.contract)
        return None if mismatch is None else f"{version}: {mismatch}"

    def fetch(self, announcement: delivery.Announcement) -> bytes:
        """The announced file, chunk by chunk; `TransferError` if any chunk fails."""
        chunks = []
        total = announcement.chunks
        for index in range(total):
            if self._stop.is_set():
                raise TransferError(f"{announcement.version}: transfer stopped (shutdown)")
            expected = min(
                announcement.chunk_bytes,
                announcement.size_bytes - index * announcement.chunk_bytes,
            )
            chunks.append(self._chunk(announcement.version, index, total, expected))
        return b"".join(chunks)

    def _chunk(self, version: str, index: int, total: int, expected: int) -> bytes:
        where = f"{version}: transfer cut at chunk {index + 1} of {total}"
        key = delivery.chunk_key(version, index, self._namespace)
        timeout = self.settings.chunk_timeout_s
        late = f"no answer within policy.chunk_timeout_s = {timeout:g}"
        asked = time.monotonic()
        try:
            replies = self._session.get(key, timeout=timeout)
            for reply in replies:
                if reply.ok is None:
                    error = reply.err.payload.to_bytes()[:200].decode(errors="replace")
                    if time.monotonic() - asked >= timeout:  # zenoh's own error at its timeout
                        raise TransferError(f"{where}: {late} (zenoh: {error})")
                    raise TransferError(f"{where}: the server answered {error!r}")
                data: bytes = reply.ok.payload.to_bytes()
                if len(data) != expected:
                    raise TransferError(f"{where}: {len(data)} bytes, expected {expected}")
                return data
        except TransferError:
            raise
        except Exception as error:  # zenoh raises its own types
            raise TransferError(f"{where}: {error}") from None
        raise TransferError(f"{where}: {late}")

    def _load(
        self, announcement: delivery.Announcement, data: bytes, contract: PolicyContract
    ) -> Candidate:
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        path = self.cache_dir / f"{announcement.version}.onnx"
        partial = path.with_suffix(".onnx.partial")
        partial.write_bytes(data)
        partial.replace(path)
        try:
            runtime = PolicyRuntime(path, backend=self.backend)
            mismatch = delivery.contract_mismatch(contract, runtime.contract)
            if mismatch is not None:
                raise PolicyFileError(f"the file's {mismatch}")
            probe(runtime)
        except PolicyFileError:
            path.unlink(missing_ok=True)  # a refused file is not kept
            raise
        return Candidate(runtime, announcement.version, announcement.sha256)

    def _refuse(self, announcement: delivery.Announcement, why: str, *, for_good: bool) -> None:
        with self.lock:
            self.status.refusals += 1
            self.status.last_refusal = why
            if for_good:
                self.status.refused[announcement.sha256] = why
        if not for_good:
            self._failed_at[announcement.sha256] = time.monotonic()
        retry = "" if for_good else f" (tried again in {self.settings.retry_interval_s:g} s)"
        self.warn("delivery", f"policy refused, the running one stays: {why}{retry}")

    def refused(self, version: str, why: str) -> None:
        """The daemon refused a candidate at the swap."""
        with self.lock:
            self.status.refusals += 1
            self.status.last_refusal = f"{version}: {why}"
            if self.status.pending == version:
                self.status.pending = None
        log.warning("policy %s refused at the swap, the running one stays: %s", version, why)

    def swapped(self, version: str) -> None:
        """The daemon swapped `version` in: the files of the versions before it go."""
        with self.lock:
            self.status.swaps += 1
            if self.status.pending == version:
                self.status.pending = None
            keep = {version, self.status.pending, self.status.fetching}
        for path in self.cache_dir.glob("*.onnx"):
            if path.stem not in keep:
                path.unlink(missing_ok=True)

    def report(self) -> dict[str, Any]:
        """The status's `delivery` object."""
        with self.lock:
            return self.status.to_dict()
