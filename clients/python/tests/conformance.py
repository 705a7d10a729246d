#!/usr/bin/env python3
"""Conformance of a real ``controller-service`` binary to the mfc.v1 contract, from Python.

    python tests/conformance.py --service-bin PATH [--json OUT] [--keep-log]

Run it with the venv's python (``setup.sh`` prints it). It writes its own service file,
starts the binary on a free loopback port (peer, no multicast scouting), connects as a
peer and checks what the .proto promises: every sample answered with its seq, partial and
law-only changes that keep the envelope, bad inputs refused each with its reason and
counted in exactly one counter, and control carrying on afterwards.

Everything is lockstep (one message, then its answer or its counter) with fixed seeds, so
the checks assert exact counts; time is only ever a generous bound on waiting. Exit status
0 iff every check passed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh  # noqa: E402

import mfc_client as mc  # noqa: E402
from mfc_client import pb  # noqa: E402
from mfc_client.reference import constant  # noqa: E402

CONTROLLER = "conf-ctl"
DEVICE = "conf-1"
GHOST = "ghost-7"
SEED = 20240611
#: Bound on waiting for one answer. Generous: the machine may be busy; a pass never depends
#: on it, only how long a failure takes to show.
WAIT = 5.0
#: Bound on waiting for a counter to move.
POLL = 15.0

# Two channels, one per kind of law, each with an envelope from its output map:
# channel 0 an iP (the intelligent law, with a warm-up), channel 1 a PID.
SERVICE_TOML = f"""
controller_id = "{CONTROLLER}"

[[devices]]
id = "{DEVICE}"
[[devices.channels]]
law = {{ law = "intelligent", params = {{ kind = "ip", alpha = 4.0, kp = 2.0 }}, estimator = {{ window = 5 }} }}
output = {{ min = -10.0, max = 10.0 }}
reference = [{{ kind = "constant", value = 1.0 }}]
[[devices.channels]]
law = {{ law = "pid", params = {{ kp = 2.0, ki = 1.0 }} }}
output = {{ min = -5.0, max = 5.0 }}
reference = [{{ kind = "smooth_step", start = 0.5, duration = 1.0, height = 0.5 }}]
"""
ENVELOPE = [(-10.0, 10.0), (-5.0, 5.0)]
# A second service with a device of its own, on the same network: a wildcard service query
# must get one reply from each, and a device's requests must reach the service serving it
# whatever the other one answers.
OTHER = "conf-ctl-2"
OTHER_DEVICE = "conf-2"
OTHER_TOML = f"""
controller_id = "{OTHER}"

[[devices]]
id = "{OTHER_DEVICE}"
[[devices.channels]]
law = {{ law = "pid", params = {{ kp = 1.0 }} }}
output = {{ min = -1.0, max = 1.0 }}
"""
NARROW = [(-8.0, 8.0), (-4.0, 4.0)]
# A third service with the fleet's secret (keys, as a deployment runs): only sealed samples
# are answered, and its commands are sealed with the device's key.
KEYED = "conf-ctl-k"
KEYED_DEVICE = "conf-k"
SECRET = bytes(range(32))
KEYED_TOML = f"""
controller_id = "{KEYED}"
secret_file = "fleet.secret"

[[devices]]
id = "{KEYED_DEVICE}"
[[devices.channels]]
law = {{ law = "pid", params = {{ kp = 1.0 }} }}
output = {{ min = -1.0, max = 1.0 }}
"""

T = TypeVar("T")


# ---- reporting ---------------------------------------------------------------------------


class Report:
    """Named checks with their details, printed as they come and summed up at the end."""

    def __init__(self) -> None:
        self.checks: list[dict[str, Any]] = []
        self.counts: dict[str, Any] = {}

    def check(self, name: str, ok: bool, detail: str = "") -> bool:
        self.checks.append({"name": name, "ok": bool(ok), "detail": detail})
        print(f"  {'PASS' if ok else 'FAIL'}  {name}" + (f": {detail}" if detail else ""), flush=True)
        return bool(ok)

    def crash(self, name: str, e: BaseException) -> None:
        self.check(name, False, f"{type(e).__name__}: {e}")

    @property
    def passed(self) -> int:
        return sum(c["ok"] for c in self.checks)

    @property
    def failed(self) -> int:
        return len(self.checks) - self.passed


# ---- the service process -----------------------------------------------------------------


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (released before the service binds it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    """The binary under test, its log in a file."""

    def __init__(self, binary: str, workdir: Path, controller: str, toml: str) -> None:
        self.controller = controller
        self.config = workdir / f"{controller}.toml"
        self.config.write_text(toml)
        self.log_path = workdir / f"{controller}.log"
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self._log = open(self.log_path, "wb")
        env = dict(os.environ)
        env.setdefault("RUST_LOG", "info,zenoh=warn")
        self.proc = subprocess.Popen(
            [binary, "--config", str(self.config), "--mode", "peer", "--listen", self.endpoint,
             "--no-multicast-scouting"],
            stdout=self._log, stderr=subprocess.STDOUT, env=env,
        )

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_serving(self, session: zenoh.Session, timeout: float) -> bool:
        """Until the liveliness token is visible and the log says "serving"."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                return False
            if "serving" in self.log() and mc.wait_for_controller(session, self.controller, 1.0):
                return True
            time.sleep(0.1)
        return False

    def stop(self) -> int | None:
        """SIGTERM, then wait (SIGKILL only if it does not stop within 10 s)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode


# ---- helpers -----------------------------------------------------------------------------


class CommandLog:
    """Every command published for any device, seen by one subscriber of its own: an
    independent witness that each sample got exactly the answers it should.

    One subscriber on the wildcard, so commands are logged in the order the service
    published them: once the log holds an answer, every answer published before it is in
    the log too, and "not answered" becomes an exact check instead of a wait.
    """

    def __init__(self, session: zenoh.Session) -> None:
        self.cond = threading.Condition()
        self.by_seq: dict[tuple[str, int], list[int]] = defaultdict(list)
        self.per_device: dict[str, int] = defaultdict(int)
        self.sub = session.declare_subscriber(f"{mc.keys.PREFIX}/device/*/command", self._on)

    def _on(self, s: zenoh.Sample) -> None:
        c = pb.Command()
        c.ParseFromString(s.payload.to_bytes())
        device = str(s.key_expr).split("/")[-2]
        with self.cond:
            self.by_seq[(device, c.seq)].append(c.mode)
            self.per_device[device] += 1
            self.cond.notify_all()

    def modes(self, seq: int, device: str = DEVICE) -> list[int]:
        """The modes of every answer to ``seq`` so far, in order."""
        with self.cond:
            return list(self.by_seq.get((device, seq), []))

    def total(self, device: str = DEVICE) -> int:
        with self.cond:
            return self.per_device[device]

    def wait_answer(self, seq: int, device: str = DEVICE, timeout: float = WAIT) -> list[int]:
        """Until the log holds an answer to ``seq`` (the plant's own subscriber may have seen
        it first); then its answers."""
        with self.cond:
            self.cond.wait_for(lambda: (device, seq) in self.by_seq, timeout)
            return list(self.by_seq.get((device, seq), []))

    def wait_count(self, n: int, device: str = DEVICE, timeout: float = WAIT) -> int:
        with self.cond:
            self.cond.wait_for(lambda: self.per_device[device] >= n, timeout)
            return self.per_device[device]


def poll(fetch: Callable[[], T], done: Callable[[T], bool], timeout: float = POLL) -> T:
    """``fetch()`` until ``done`` holds or the timeout passes; the last value either way."""
    deadline = time.monotonic() + timeout
    value = fetch()
    while not done(value) and time.monotonic() < deadline:
        time.sleep(0.05)
        value = fetch()
    return value


def mode_name(m: int) -> str:
    return pb.Mode.Name(m) if m in pb.Mode.values() else str(m)


def limits_of(env: pb.Envelope) -> list[tuple[float | None, float | None]]:
    return [
        (c.min if c.HasField("min") else None, c.max if c.HasField("max") else None)
        for c in env.channels
    ]


def map_limits(cfg: pb.DeviceConfig) -> list[tuple[float | None, float | None]]:
    return [
        (c.output.min if c.output.HasField("min") else None,
         c.output.max if c.output.HasField("max") else None)
        for c in cfg.channels
    ]


class Lag:
    """Two first-order lags, y' = (-y + k v) / tau, integrated exactly over each period: the
    plant the good samples come from (deterministic)."""

    def __init__(self, k: float = 2.0, tau: float = 0.5) -> None:
        self.k, self.tau = k, tau
        self.y = [0.0, 0.0]

    def step(self, v: list[float], dt: float) -> list[float]:
        a = math.exp(-dt / self.tau)
        self.y = [a * y + (1 - a) * self.k * vi for y, vi in zip(self.y, v)]
        return list(self.y)


# ---- the test ----------------------------------------------------------------------------


class Conformance:
    def __init__(self, session: zenoh.Session, report: Report) -> None:
        self.s = session
        self.r = report
        self.op = mc.Operator(session, timeout=WAIT)
        rng = random.Random(SEED)
        self.link = mc.PlantLink(session, DEVICE, run_id=rng.getrandbits(63) + 1)
        self.log = CommandLog(session)
        self.plant = Lag()
        self.v = [0.0, 0.0]
        self.h = 0.01
        self.t = 0.0
        # Samples sent that must each get exactly one non-REJECTED answer.
        self.good_seqs: list[int] = []
        # Samples that must each get exactly one REJECTED answer.
        self.rejected_seqs: list[int] = []
        # requests_refused before the refused changes. Not 0: what the service counts for a
        # query about a device it does not serve (the discovery phase sends one) is not part
        # of the contract, so only the changes refused from here on are counted exactly.
        self.refused_base = 0

    # One good exchange of the plant; the answer, or None.
    def good(self, outputs: list[float] | None = None) -> pb.Command | None:
        self.t += self.h
        y = self.plant.step(self.v, self.h) if outputs is None else outputs
        cmd = self.link.exchange(y, self.v, self.t, WAIT)
        self.good_seqs.append(self.last_sent().seq)
        if cmd is not None and cmd.mode == pb.MODE_CONTROL:
            self.v = list(cmd.v)
        return cmd

    # One refused sample: built by `mutate` from the next good one, its seq not consumed (a
    # refused sample changes no state, so the next good sample may use the same number).
    def bad(self, mutate: Callable[[pb.Sample], None]) -> pb.Command | None:
        s = self.link.sample(self.plant.y, self.v, self.t + self.h)
        mutate(s)
        self.link.publish(s)
        return self.link.wait(s.seq, WAIT)

    def service(self) -> pb.ServiceStatus:
        return self.op.service(CONTROLLER)

    def last_sent(self) -> pb.Sample:
        assert self.link.last_sent is not None
        return self.link.last_sent

    # ---- the phases ----------------------------------------------------------------------

    def run(self) -> None:
        phases = [
            ("discovery", self.discovery),
            ("lockstep", self.lockstep),
            ("partial change", self.partial_change),
            ("law-only change", self.law_only_change),
            ("refused samples", self.refused_samples),
            ("dropped messages", self.dropped_messages),
            ("unknown device", self.unknown_device),
            ("envelope", self.envelope),
            ("refused requests", self.refused_requests),
            ("control resumes", self.control_resumes),
            ("counters", self.counters),
        ]
        for name, phase in phases:
            print(f"{name}:", flush=True)
            try:
                phase()
            except Exception as e:  # noqa: BLE001 - a crash is a failed check, not the end
                self.r.crash(f"{name} (no exception)", e)

    def discovery(self) -> None:
        # The raw wildcard query first: one reply per service, each on its own key.
        got = []
        for reply in self.s.get(mc.keys.service_status("*"), target=zenoh.QueryTarget.ALL,
                                consolidation=zenoh.ConsolidationMode.NONE, timeout=WAIT):
            if reply.ok is not None:
                st = pb.ServiceStatus()
                st.ParseFromString(reply.ok.payload.to_bytes())
                got.append((str(reply.ok.key_expr), st.controller_id))
        want = sorted((mc.keys.service_status(c), c) for c in (CONTROLLER, OTHER, KEYED))
        self.r.check("wildcard service status: one reply per service, each on its own key",
                     sorted(got) == want, f"{sorted(got)}")
        services = self.op.services(timeout=WAIT)
        devs = {s.controller_id: [d.device_id for d in s.devices] for s in services}
        self.r.check("Operator.services(): each service with its declared device",
                     devs == {CONTROLLER: [DEVICE], OTHER: [OTHER_DEVICE], KEYED: [KEYED_DEVICE]},
                     f"{devs}")
        other = self.op.config(OTHER_DEVICE)
        self.r.check("a device's config comes from the service serving it (the other refuses)",
                     other.device_id == OTHER_DEVICE and map_limits(other) == [(-1.0, 1.0)],
                     f"{other.device_id} {map_limits(other)}")
        cfg = self.op.config(DEVICE)
        self.r.check(
            "config read: envelope from the output maps",
            limits_of(cfg.envelope) == ENVELOPE and map_limits(cfg) == ENVELOPE,
            f"envelope {limits_of(cfg.envelope)}, maps {map_limits(cfg)}",
        )

    def lockstep(self, n: int = 300) -> None:
        answered, wrong, modes = 0, list[str](), defaultdict[str, int](int)
        for _ in range(n):
            cmd = self.good()
            sent_ns = self.last_sent().sent_unix_ns
            if cmd is None:
                continue
            answered += 1
            modes[mode_name(cmd.mode)] += 1
            ok = (
                cmd.version == mc.PROTOCOL_VERSION and cmd.device_id == DEVICE
                and cmd.controller_id == CONTROLLER and cmd.sample_sent_unix_ns == sent_ns
                and cmd.mode in (pb.MODE_CONTROL, pb.MODE_WARMING_UP)
                and len(cmd.v) == 2 and len(cmd.u) == 2
            )
            if not ok and len(wrong) < 3:
                wrong.append(str(cmd).replace("\n", " "))
        self.r.counts["lockstep"] = {"sent": n, "answered": answered, "modes": dict(modes)}
        self.r.check(f"every sample answered with its seq ({answered}/{n})", answered == n)
        self.r.check("answers echo version, ids and sent_unix_ns; mode CONTROL or WARMING_UP",
                     not wrong, "; ".join(wrong))
        total = self.log.wait_count(n)
        self.log.wait_answer(self.good_seqs[-1])
        dup = [q for q in self.good_seqs if len(self.log.modes(q)) != 1]
        self.r.check(f"exactly one command per sample on the wire ({total} for {n})",
                     total == n and not dup, f"seqs answered other than once: {dup[:5]}")
        self.r.check("control after the warm-up", modes.get("MODE_CONTROL", 0) > 0
                     and self.log.wait_answer(self.good_seqs[-1]) == [pb.MODE_CONTROL], f"{dict(modes)}")
        st = self.op.status(DEVICE)
        got = (st.last_seq, st.lost, st.duplicates, st.stale, st.rejected, st.restarts)
        self.r.check("device status after the lockstep: last_seq 300, nothing lost/duplicate/"
                     "stale/rejected, one run", got == (n, 0, 0, 0, 0, 1),
                     f"(last_seq, lost, duplicates, stale, rejected, restarts) = {got}")

    def partial_change(self) -> None:
        before = self.op.config(DEVICE)
        after = self.op.update(DEVICE, 0, kp=3.5)
        law = after.channels[0].intelligent
        read = self.op.config(DEVICE)
        self.r.check(
            "partial change: one gain changes, read back",
            law.kp == 3.5 and read.channels[0].intelligent.kp == 3.5,
            f"kp {law.kp}, read back {read.channels[0].intelligent.kp}",
        )
        kept = (
            law.alpha == before.channels[0].intelligent.alpha
            and after.channels[0].output == before.channels[0].output
            and after.channels[1] == before.channels[1]
            and after.reference == before.reference
        )
        self.r.check("partial change keeps every other value (alpha, maps, channel 1, reference)",
                     kept, f"alpha {law.alpha}")
        self.r.check("partial change keeps the envelope and output limits",
                     limits_of(read.envelope) == ENVELOPE and map_limits(read) == ENVELOPE,
                     f"envelope {limits_of(read.envelope)}, maps {map_limits(read)}")
        cmd = self.good()
        self.r.check("control carries on after the change (bumpless, no warm-up)",
                     cmd is not None and cmd.mode == pb.MODE_CONTROL,
                     mode_name(cmd.mode) if cmd else "no answer")
        # A named operator's change is on the record under its name (unverified: this
        # service has no access section), with the old and new gain.
        named = mc.Operator(self.op.session, timeout=WAIT, operator="pyop")
        named.update(DEVICE, 0, kp=3.75)
        last = named.audit(DEVICE)[-1]
        moved = [(c.what, c.old, c.new) for c in last.changes]
        self.r.check("a named change is audited: operator, unverified, old and new gain",
                     last.operator == "pyop" and not last.verified and last.accepted
                     and ("channel 0 kp", "3.5", "3.75") in moved,
                     f"{last}")

    def law_only_change(self, n: int = 60) -> None:
        cfg = self.op.set_channels(DEVICE, [pb.Pid(kp=1e6), pb.Pid(kp=1e6)])
        self.r.check(
            "law-only channels change keeps the output limits and the envelope",
            all(c.WhichOneof("law") == "pid" and c.pid.kp == 1e6 for c in cfg.channels)
            and map_limits(cfg) == ENVELOPE and limits_of(cfg.envelope) == ENVELOPE,
            f"laws {[c.WhichOneof('law') for c in cfg.channels]}, maps {map_limits(cfg)}, "
            f"envelope {limits_of(cfg.envelope)}",
        )
        inside, hit, answered = True, [False, False], 0
        for k in range(n):
            y = 100.0 if k % 7 < 3 else -50.0
            cmd = self.good([y, -y])
            if cmd is None or cmd.mode != pb.MODE_CONTROL:
                continue
            answered += 1
            for i, (lo, hi) in enumerate(ENVELOPE):
                inside &= lo <= cmd.v[i] <= hi
                hit[i] |= cmd.v[i] in (lo, hi)
        self.r.check(f"gain 1e6 on a huge error: every command inside the envelope ({answered}/{n} "
                     "CONTROL)", inside and answered == n)
        self.r.check("the huge gain is in force (each channel saturates at its limit)", all(hit), f"{hit}")

    def refused_samples(self) -> None:
        cases: list[tuple[str, Callable[[pb.Sample], None], str]] = [
            ("NaN output", lambda s: s.outputs.__setitem__(0, math.nan), "non-finite"),
            ("wrong channel count", lambda s: s.outputs.pop(), ""),
            ("device_id other than the key's", lambda s: setattr(s, "device_id", "someone-else"), "device id"),
            ("seq jump of 2^64-1", lambda s: setattr(s, "seq", 2**64 - 1), "jump"),
        ]
        for name, mutate, needle in cases:
            cmd = self.bad(mutate)
            if cmd is not None:
                self.rejected_seqs.append(cmd.seq)
            ok = (cmd is not None and cmd.mode == pb.MODE_REJECTED and len(cmd.v) == 0
                  and cmd.error != "" and needle in cmd.error)
            detail = (f"{mode_name(cmd.mode)} {cmd.error!r}" if cmd else "no answer")
            self.r.check(f"{name} -> REJECTED" + (f" mentioning {needle!r}" if needle else " with a reason"),
                         ok, detail)
        cmd = self.good()
        self.r.check("the next good sample is in control (no restart, no warm-up)",
                     cmd is not None and cmd.mode == pb.MODE_CONTROL,
                     mode_name(cmd.mode) if cmd else "no answer")

    def dropped_messages(self) -> None:
        base = self.service()
        # Another protocol version: not answered, counted as undecodable.
        seq = self.link.next_seq
        self.bad_publish(lambda s: setattr(s, "version", 2))
        st = poll(self.service, lambda s: s.undecodable > base.undecodable)
        self.r.check("sample of protocol version 2 -> counted in undecodable",
                     st.undecodable == base.undecodable + 1, f"{base.undecodable} -> {st.undecodable}")
        cmd = self.good()
        self.r.check("...and not answered (the same seq sent well gets the only answer)",
                     cmd is not None and self.log.wait_answer(seq) == [pb.MODE_CONTROL],
                     f"answers to seq {seq}: {[mode_name(m) for m in self.log.modes(seq)]}")
        # Over the size limit: dropped unread, counted as oversized.
        seq = self.link.next_seq
        big = self.link.sample([0.0] * 9000, [], self.t + self.h).SerializeToString()
        self.s.put(mc.keys.sample(DEVICE), big, congestion_control=zenoh.CongestionControl.BLOCK)
        st = poll(self.service, lambda s: s.oversized > base.oversized)
        self.r.check(f"payload of {len(big)} bytes (> {mc.MAX_PAYLOAD}) -> counted in oversized",
                     len(big) > mc.MAX_PAYLOAD and st.oversized == base.oversized + 1,
                     f"{base.oversized} -> {st.oversized}")
        cmd = self.good()
        self.r.check("...and not answered", cmd is not None and self.log.wait_answer(seq) == [pb.MODE_CONTROL],
                     f"answers to seq {seq}: {[mode_name(m) for m in self.log.modes(seq)]}")

    def bad_publish(self, mutate: Callable[[pb.Sample], None]) -> None:
        s = self.link.sample(self.plant.y, self.v, self.t + self.h)
        mutate(s)
        self.link.publish(s)

    def unknown_device(self) -> None:
        base = self.service()
        with mc.PlantLink(self.s, GHOST, run_id=7) as ghost:
            ghost.send([0.0], [], 0.01)
            st = poll(self.service, lambda s: s.unknown_samples > base.unknown_samples)
            self.r.check("sample on an unknown device's key -> counted in unknown_samples",
                         st.unknown_samples == base.unknown_samples + 1 and GHOST in st.unknown_devices,
                         f"{base.unknown_samples} -> {st.unknown_samples}, {list(st.unknown_devices)}")
            # The good device's next answer is published after the ghost's sample was handled,
            # so once the log holds it, an answer to the ghost would be there too.
            self.good()
            self.log.wait_answer(self.last_sent().seq)
            n = self.log.total(GHOST)
            self.r.check("...and not answered", n == 0, f"{n} commands")
        try:
            st = self.op.status(GHOST)
            self.r.check("status of an unknown device -> error reply", False, f"got a status: {st.device_id}")
        except mc.ErrorReply as e:
            self.r.check("status of an unknown device -> error reply naming it", GHOST in e.text, repr(e.text))
            self.r.counts["unknown_status_error"] = e.text

    def envelope(self) -> None:
        self.refused_base = self.service().requests_refused
        self.r.counts["requests_refused_before_changes"] = self.refused_base
        try:
            env = self.op.change_envelope(DEVICE, [(-20.0, 20.0, None), (-5.0, 5.0, None)], "conformance: widen")
            self.r.check("envelope widening refused", False, f"accepted: {limits_of(env)}")
        except mc.Refused as e:
            self.r.check("envelope widening refused mentioning allow_remote_widening",
                         "allow_remote_widening" in e.reason, repr(e.reason))
        self.r.check("...and nothing changed", limits_of(self.op.envelope(DEVICE)) == ENVELOPE,
                     f"{limits_of(self.op.envelope(DEVICE))}")
        env = self.op.change_envelope(DEVICE, [(lo, hi, None) for lo, hi in NARROW], "conformance: narrow")
        st = self.op.status(DEVICE)
        cfg = self.op.config(DEVICE)
        self.r.check("envelope narrowing accepted", limits_of(env) == NARROW, f"{limits_of(env)}")
        self.r.check("...reflected in the device status (envelope, envelope_changes 1)",
                     limits_of(st.envelope) == NARROW and st.envelope_changes == 1,
                     f"{limits_of(st.envelope)}, changes {st.envelope_changes}")
        self.r.check("...output maps narrowed to fit", map_limits(cfg) == NARROW, f"{map_limits(cfg)}")

    def refused_requests(self) -> None:
        before = self.op.config(DEVICE)
        try:
            self.op.set_reference(DEVICE, [[constant(1.0)]])
            self.r.check("reference for 1 channel of 2 (query) refused", False, "accepted")
        except mc.Refused as e:
            self.r.check("reference for 1 channel of 2 (query) refused with a reason",
                         e.reason != "" and "channel" in e.reason, repr(e.reason))
        try:
            self.op.update(DEVICE, 1, alpha=2.0)
            self.r.check("alpha on a PID refused", False, "accepted")
        except mc.Refused as e:
            self.r.check("alpha on a PID refused naming it", "alpha" in e.reason, repr(e.reason))
        self.r.check("refused requests changed nothing", self.op.config(DEVICE) == before)
        # And an accepted reference (query) for contrast: the answer is the new configuration.
        cfg = self.op.set_reference(DEVICE, [[constant(0.5)], [constant(-0.5)]], start_time=self.t)
        pieces = [c.pieces[0].constant.value for c in cfg.reference.channels]
        self.r.check("reference query accepted and answered with the new configuration",
                     pieces == [0.5, -0.5], f"{pieces}")

    def control_resumes(self, n: int = 50) -> None:
        modes, inside = defaultdict[str, int](int), True
        for k in range(n):
            y = 100.0 if k % 5 < 2 else -100.0
            cmd = self.good([y, -y])
            modes[mode_name(cmd.mode) if cmd else "none"] += 1
            if cmd is not None and cmd.mode == pb.MODE_CONTROL:
                inside &= all(lo <= v <= hi for v, (lo, hi) in zip(cmd.v, NARROW))
        self.r.counts["final"] = {"sent": n, "modes": dict(modes)}
        self.r.check(f"the good device still gets CONTROL commands ({modes.get('MODE_CONTROL', 0)}/{n})",
                     modes.get("MODE_CONTROL", 0) == n, f"{dict(modes)}")
        self.r.check("...inside the narrowed envelope", inside)

    def counters(self) -> None:
        total = len(self.good_seqs) + len(self.rejected_seqs)
        self.log.wait_count(total)
        self.log.wait_answer(self.good_seqs[-1])
        # A refused sample and the good one after it share a seq: count the answers that are
        # not REJECTED, one per good sample.
        once = [q for q in self.good_seqs
                if len([m for m in self.log.modes(q) if m != pb.MODE_REJECTED]) != 1]
        self.r.check(f"every good sample answered exactly once ({len(self.good_seqs)} samples, "
                     f"{self.log.total()} commands incl. {len(self.rejected_seqs)} REJECTED)",
                     not once and self.log.total() == total, f"not once: {once[:5]}")
        st = self.service()
        dev = next((d for d in st.devices if d.device_id == DEVICE), pb.DeviceStatus())
        svc = {f: getattr(st, f) for f in ("undecodable", "oversized", "unknown_samples", "rejected",
                                           "requests_refused", "bad_key", "queue_full",
                                           "device_table_full", "superseded")}
        svc["unknown_devices"] = list(st.unknown_devices)
        want = {"undecodable": 1, "oversized": 1, "unknown_samples": 1, "rejected": 4,
                "requests_refused": self.refused_base + 3, "bad_key": 0, "queue_full": 0, "device_table_full": 0,
                "unknown_devices": [GHOST]}
        bad = {k: (svc[k], v) for k, v in want.items() if svc[k] != v}
        self.r.check("service counters: each dropped or refused message in exactly one counter",
                     not bad, f"(got, want) {bad}" if bad else json.dumps(svc))
        d = {f: getattr(dev, f) for f in ("samples", "commands", "lost", "duplicates", "stale", "rejected",
                                          "restarts", "envelope_changes", "clamped", "references_refused",
                                          "superseded", "samples_off_remote")}
        dwant = {"lost": 0, "duplicates": 0, "stale": 0, "rejected": 4, "restarts": 1,
                 "envelope_changes": 1, "clamped": 0, "references_refused": 1, "samples_off_remote": 0}
        dbad = {k: (d[k], v) for k, v in dwant.items() if d[k] != v}
        self.r.check("device counters", not dbad, f"(got, want) {dbad}" if dbad else json.dumps(d))
        self.r.counts["service"] = svc
        self.r.counts["device"] = d
        self.r.counts["good_samples"] = len(self.good_seqs)
        self.r.counts["rejected_samples"] = len(self.rejected_seqs)
        self.r.counts["commands_seen"] = self.log.total()


def example_plant(report: Report, binary: str, tmp: Path) -> Service:
    """The shipped example as a user runs it: `examples/first_order_plant.py` (the paced
    loop of `PlantLink.run`) against a service started from `examples/service.toml`."""
    examples = Path(__file__).resolve().parents[1] / "examples"
    sv = Service(binary, tmp, "py-ctl", (examples / "service.toml").read_text())
    session = mc.connect(connect=[sv.endpoint])
    try:
        if report.check("example service up", sv.wait_serving(session, 60.0)):
            run_example(report, session, sv, examples)
    finally:
        session.close()
    return sv


def run_example(report: Report, session: zenoh.Session, sv: Service, examples: Path) -> None:
    seconds, rate = 3.0, 100.0
    run = subprocess.run(
        [sys.executable, str(examples / "first_order_plant.py"), "--connect", sv.endpoint,
         "--seconds", str(seconds), "--rate", str(rate)],
        capture_output=True, text=True, timeout=120,
    )
    out = run.stdout + run.stderr
    print("    " + "\n    ".join(out.strip().splitlines()), flush=True)
    report.check("example plant exits 0 (it was controlled)", run.returncode == 0,
                 f"exit {run.returncode}")
    # "commands: N arrived in time (C control, ...)": the paced loop was answered. Counts,
    # not timing: on a busy machine some answers come after their period, so the bound is
    # half the periods, where a loop nobody answers gets none.
    m = re.search(r"commands: (\d+) arrived in time \((\d+) control", out)
    steps = int(seconds * rate)
    report.check("example plant: at least half its periods answered in time, a third with CONTROL",
                 bool(m) and int(m.group(1)) >= steps // 2 and int(m.group(2)) >= steps // 3,
                 m.group(0) if m else "no summary line")
    st = device_status(session, "py-1")
    report.check("the service counted the example's samples",
                 st is not None and st.samples >= steps // 2 and st.rejected == 0,
                 f"samples {st.samples if st else None}, rejected {st.rejected if st else None}")


def device_status(session: zenoh.Session, device: str) -> pb.DeviceStatus | None:
    try:
        return mc.Operator(session).status(device)
    except mc.MfcError:
        return None


def keyed(session: zenoh.Session, report: Report) -> None:
    """Against the service with keys: a link with the device's key is answered, with sealed
    commands; an unsealed sample and one sealed under another key are dropped unread and
    counted as forged; an unsealed command on the device's key is dropped by the link."""
    op = mc.Operator(session, timeout=WAIT)
    key = mc.auth.device_key(SECRET, KEYED_DEVICE)
    link = mc.PlantLink(session, KEYED_DEVICE, key=key)
    answers = [link.exchange([0.1], [0.0], 0.01 * (k + 1), WAIT) for k in range(5)]
    report.check("a sealed sample is answered, its command sealed with the device's key",
                 all(a is not None for a in answers) and link.stats.forged == 0,
                 f"{sum(a is not None for a in answers)}/5 answered, {link.stats.forged} forged")
    base = op.service(KEYED).forged
    open_link = mc.PlantLink(session, KEYED_DEVICE, run_id=link.run_id)
    got = open_link.exchange([0.1], [0.0], 1.0, 1.0)
    wrong = mc.PlantLink(session, KEYED_DEVICE, run_id=link.run_id, key=bytes(32))
    got2 = wrong.exchange([0.1], [0.0], 1.0, 1.0)
    st = poll(lambda: op.service(KEYED), lambda s: s.forged >= base + 2)
    report.check("an unsealed sample and one under another key: unanswered, counted as forged",
                 got is None and got2 is None and st.forged == base + 2 and st.authenticated,
                 f"answers {got is not None}/{got2 is not None}, forged {st.forged - base}")
    forged_cmd = pb.Command(version=mc.PROTOCOL_VERSION, device_id=KEYED_DEVICE,
                            seq=link.next_seq, mode=pb.MODE_CONTROL, v=[1.0])
    session.put(mc.keys.command(KEYED_DEVICE), forged_cmd.SerializeToString())
    seq = link.send([0.1], [0.0], 2.0)
    cmd = link.wait(seq, WAIT)
    report.check("an unsealed command is dropped by a link with a key, the real one taken",
                 cmd is not None and link.stats.forged == 1,
                 f"answer {cmd is not None}, forged {link.stats.forged}")
    for ln in (link, open_link, wrong):
        ln.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--service-bin", required=True, help="path of the controller-service binary")
    ap.add_argument("--json", help="write a JSON summary here")
    ap.add_argument("--keep-log", action="store_true", help="print the service's log at the end")
    args = ap.parse_args()
    binary = str(Path(args.service_bin).resolve())
    if not os.access(binary, os.X_OK):
        print(f"conformance: {binary} is not an executable", file=sys.stderr)
        return 2

    report = Report()
    started = time.monotonic()
    logs: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="mfc-conformance-") as tmp:
        (Path(tmp) / "fleet.secret").write_text(SECRET.hex() + "\n")
        services = [Service(binary, Path(tmp), CONTROLLER, SERVICE_TOML),
                    Service(binary, Path(tmp), OTHER, OTHER_TOML),
                    Service(binary, Path(tmp), KEYED, KEYED_TOML)]
        session = None
        try:
            session = mc.connect(connect=[sv.endpoint for sv in services])
            up = True
            for sv in services:
                ok = sv.wait_serving(session, 60.0)
                up &= report.check(f"service {sv.controller} up on {sv.endpoint} (liveliness token, "
                                   "\"serving\")", ok, "" if ok else f"exit {sv.proc.poll()}")
            if up:
                Conformance(session, report).run()
                print("keys:", flush=True)
                try:
                    keyed(session, report)
                except Exception as e:  # noqa: BLE001
                    report.crash("keys (no exception)", e)
                print("example plant:", flush=True)
                services.append(example_plant(report, binary, Path(tmp)))
        except Exception as e:  # noqa: BLE001
            report.crash("harness", e)
        finally:
            if session is not None:
                session.close()
            codes = {sv.controller: sv.stop() for sv in services}
        for c, code in codes.items():
            report.check(f"service {c} stops cleanly on SIGTERM (exit 0)", code == 0, f"exit {code}")
        logs = {sv.controller: sv.log_path.read_text(errors="replace") for sv in services}
    elapsed = time.monotonic() - started

    print(f"\nconformance: {report.passed} passed, {report.failed} failed "
          f"({len(report.checks)} checks, {elapsed:.1f} s)")
    if report.failed or args.keep_log:
        for c, log in logs.items():
            print(f"---- service {c}: log (last 40 lines) ----")
            print("\n".join(log.splitlines()[-40:]))
    if args.json:
        summary = {
            "passed": report.passed,
            "failed": report.failed,
            "seconds": round(elapsed, 2),
            "service_bin": binary,
            "checks": report.checks,
            "counts": report.counts,
        }
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
    return 0 if report.failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
