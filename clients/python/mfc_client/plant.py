"""The plant's end of the loop: publish a Sample every period, take the Command answering it.

The controller answers each sample with a command carrying the same ``seq``; anything else
that arrives (an answer to an older sample that came late) must not be applied, so the link
waits for the one command that answers the sample it just sent.
"""

from __future__ import annotations

import math
import queue
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import zenoh

from . import auth, keys
from ._pb import PROTOCOL_VERSION, pb

#: What ``step_fn`` of :meth:`PlantLink.run` is: ``(t, dt, v) -> outputs``.
StepFn = Callable[[float, float, Sequence[float]], Sequence[float]]


def new_run_id() -> int:
    """A random nonzero 64-bit run id.

    A new value tells the controller that the plant restarted (its ``seq`` starts again), so
    it rebuilds the device's state instead of calling every new sample stale. 0 means "not
    set" on the wire, hence never returned.
    """
    while True:
        r = secrets.randbits(64)
        if r:
            return r


def unix_ns() -> int:
    """Wall clock in Unix nanoseconds (``sent_unix_ns``, echoed back for round-trip timing)."""
    return time.time_ns()


@dataclass
class LinkStats:
    """What the link saw of the commands (counts since it was made)."""

    #: Commands received on the device's command key (any seq).
    received: int = 0
    #: Commands answering a sample this link had stopped waiting for (too late), or a seq it
    #: did not send: dropped, never returned.
    ignored: int = 0
    #: Payloads that did not decode or carried another protocol version.
    undecodable: int = 0
    #: With a key: commands dropped unread, unsealed or sealed under another key.
    forged: int = 0


@dataclass
class RunStats:
    """The outcome of :meth:`PlantLink.run`."""

    steps: int = 0
    #: Answers by mode (answers that came in time).
    control: int = 0
    warming_up: int = 0
    rejected: int = 0
    stale: int = 0
    #: Periods whose answer did not come before the next deadline (the last value was held).
    missing: int = 0
    #: Periods that started more than half a period after their deadline (this process was
    #: too slow: the loop skips no period, it just runs late).
    overruns: int = 0
    #: Round trips of answered samples (microseconds).
    rtt_us: list[int] = field(default_factory=list)
    #: The last refusal reason (``Command.error``), if any.
    last_error: str = ""

    @property
    def answered(self) -> int:
        """Samples answered in time, whatever the mode."""
        return self.control + self.warming_up + self.rejected + self.stale


class PlantLink:
    """Samples out, commands in, for one device.

    Samples and commands are control traffic: they go out ``express`` (no batching), at
    ``RealTime`` priority, with ``Drop`` congestion control, as on the Rust side: in a
    control loop a stale message is worse than a lost one, and a blocked publisher must
    never stall the loop.

    Each link is one plant run: a random nonzero ``run_id`` and ``seq`` counting up from
    ``first_seq``. Make a new link (or pass a new ``run_id``) when the plant restarts.
    """

    def __init__(
        self,
        session: zenoh.Session,
        device_id: str,
        *,
        run_id: int | None = None,
        first_seq: int = 1,
        key: bytes | None = None,
    ) -> None:
        self.device_id = keys.check_id(device_id)
        #: The device's key (:mod:`mfc_client.auth`): samples go out sealed, and only
        #: commands sealed with it are taken. None: the link runs open.
        self.key = key
        self.run_id = new_run_id() if run_id is None else run_id
        self.last_rtt_us = 0
        self.stats = LinkStats()
        #: The last Sample published (its ``sent_unix_ns`` is echoed in the answer).
        self.last_sent: pb.Sample | None = None
        self._next_seq = first_seq
        # seq -> monotonic time it was sent, for the round trip; only the last few are kept.
        self._sent: dict[int, float] = {}
        self._inbox: queue.Queue[tuple[bytes, float]] = queue.Queue()
        self._publisher = session.declare_publisher(
            keys.sample(device_id),
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME,
            express=True,
        )
        # The callback only stamps and queues: it runs on zenoh's side and must not block.
        self._subscriber = session.declare_subscriber(
            keys.command(device_id),
            lambda s: self._inbox.put((s.payload.to_bytes(), time.monotonic())),
        )

    # ---- one exchange ------------------------------------------------------------------

    @property
    def next_seq(self) -> int:
        """The ``seq`` the next :meth:`send` will use."""
        return self._next_seq

    def sample(
        self,
        outputs: Sequence[float],
        applied: Sequence[float] = (),
        plant_time: float = 0.0,
        *,
        flags: int = 0,
        seq: int | None = None,
    ) -> pb.Sample:
        """Build a Sample of this run (``seq`` defaults to :attr:`next_seq`, not consumed)."""
        return pb.Sample(
            version=PROTOCOL_VERSION,
            device_id=self.device_id,
            seq=self._next_seq if seq is None else seq,
            plant_time=plant_time,
            outputs=list(outputs),
            applied=list(applied),
            flags=flags,
            sent_unix_ns=unix_ns(),
            last_rtt_us=self.last_rtt_us,
            run_id=self.run_id,
        )

    def publish(self, message: pb.Sample | bytes) -> None:
        """Publish a Sample as it is, or raw bytes, on the device's sample key.

        The low-level door, for tests of what a controller refuses; :meth:`send` is the
        normal way.
        """
        if isinstance(message, pb.Sample):
            self.last_sent = message
            self._sent[message.seq] = time.monotonic()
            if len(self._sent) > 256:
                self._sent.pop(next(iter(self._sent)))
            message = message.SerializeToString()
            if self.key is not None:
                message = auth.seal(self.key, auth.SAMPLE, message)
        self._publisher.put(message)

    def send(
        self,
        outputs: Sequence[float],
        applied: Sequence[float] = (),
        plant_time: float = 0.0,
        *,
        flags: int = 0,
    ) -> int:
        """Publish the next sample of this run; returns its ``seq``."""
        s = self.sample(outputs, applied, plant_time, flags=flags)
        self._next_seq += 1
        self.publish(s)
        return s.seq

    def wait(self, seq: int, timeout: float) -> pb.Command | None:
        """The command answering ``seq``, or None if none came within ``timeout`` seconds.

        Commands for other sequence numbers (answers that came too late) are dropped and
        counted in :attr:`stats`. The round trip of the answer is kept and reported in the
        next sample (``last_rtt_us``).
        """
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                raw, t_recv = self._inbox.get(timeout=left) if left > 0 else self._inbox.get_nowait()
            except queue.Empty:
                return None
            if self.key is not None:
                body = auth.open_sealed(self.key, auth.COMMAND, raw)
                if body is None:
                    self.stats.forged += 1
                    continue
                raw = body
            cmd = pb.Command()
            try:
                cmd.ParseFromString(raw)
            except Exception:  # noqa: BLE001 - any garbage is just counted
                self.stats.undecodable += 1
                continue
            if cmd.version != PROTOCOL_VERSION:
                self.stats.undecodable += 1
                continue
            self.stats.received += 1
            sent = self._sent.get(seq)
            # Another seq, or one that arrived before this sample went out (the answer to an
            # earlier sample with the same number): not the answer to this sample.
            if cmd.seq != seq or (sent is not None and t_recv < sent):
                self.stats.ignored += 1
                continue
            if sent is not None:
                self.last_rtt_us = min(int((t_recv - sent) * 1e6), 2**32 - 1)
            return cmd

    def exchange(
        self,
        outputs: Sequence[float],
        applied: Sequence[float] = (),
        plant_time: float = 0.0,
        timeout: float = 1.0,
        *,
        flags: int = 0,
    ) -> pb.Command | None:
        """Send one sample and wait for the command answering it (None on timeout)."""
        return self.wait(self.send(outputs, applied, plant_time, flags=flags), timeout)

    # ---- a paced loop ------------------------------------------------------------------

    def run(
        self,
        period: float,
        steps: int,
        step_fn: StepFn,
        *,
        initial: Sequence[float] | None = None,
        on_command: Callable[[int, pb.Command | None], None] | None = None,
    ) -> RunStats:
        """Run the loop for ``steps`` periods of ``period`` seconds, paced on absolute deadlines.

        Deadline ``k`` is ``start + k * period`` on ``time.monotonic()``, so a slow period
        does not shift every later one (no drift). At each deadline:

        1. ``step_fn(t, dt, v)`` advances the plant by ``dt`` (0 at the first step) with the
           values ``v`` held over that interval, and returns its outputs at plant time ``t``
           (``k * period``);
        2. the sample (outputs, and ``v`` as ``applied``) goes out;
        3. the answer is awaited until the next deadline. A CONTROL command sets ``v``;
           WARMING_UP, REJECTED, STALE or no answer at all hold the last ``v`` (the next
           sample then says so with ``SAMPLE_FLAGS_HOLDING`` if a command was missing or
           refused after control had begun).

        ``v`` starts at ``initial`` (zeros by default). ``on_command(k, cmd)`` is called with
        every period's answer (None when it did not come in time).
        """
        if period <= 0 or not math.isfinite(period):
            raise ValueError(f"period {period}: must be a positive number of seconds")
        stats = RunStats()
        v: list[float] | None = list(initial) if initial is not None else None
        holding = False
        controlled = False
        start = time.monotonic()
        for k in range(steps):
            deadline = start + k * period
            now = time.monotonic()
            if now < deadline:
                time.sleep(deadline - now)
            elif now > deadline + period / 2:
                stats.overruns += 1
            t = k * period
            y = list(step_fn(t, period if k else 0.0, v if v is not None else []))
            if v is None:
                v = [0.0] * len(y)
            flags = pb.SAMPLE_FLAGS_HOLDING if holding else pb.SAMPLE_FLAGS_NONE
            seq = self.send(y, v, t, flags=flags)
            cmd = self.wait(seq, start + (k + 1) * period - time.monotonic())
            stats.steps += 1
            if on_command is not None:
                on_command(k, cmd)
            if cmd is None:
                stats.missing += 1
                holding = controlled
                continue
            stats.rtt_us.append(self.last_rtt_us)
            if cmd.mode == pb.MODE_CONTROL and len(cmd.v) == len(v):
                stats.control += 1
                v = list(cmd.v)
                holding, controlled = False, True
            elif cmd.mode == pb.MODE_WARMING_UP:
                stats.warming_up += 1
            elif cmd.mode == pb.MODE_STALE:
                stats.stale += 1
            else:
                stats.rejected += 1
                stats.last_error = cmd.error
                holding = controlled
        return stats

    def close(self) -> None:
        """Undeclare the publisher and the subscriber (the session stays open)."""
        self._subscriber.undeclare()
        self._publisher.undeclare()

    def __enter__(self) -> PlantLink:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
