"""The operator's side: read and change a device's configuration, envelope and reference,
and read the status of devices and services.

Everything here is request/reply (zenoh queries), never the control path. A change is all
or nothing on the controller: when it is refused nothing changed, and the reason comes
back; this module raises it as :class:`Refused` so that a script cannot carry on believing
a gain was set.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import zenoh
from google.protobuf.message import DecodeError, Message

from . import keys
from ._pb import PROTOCOL_VERSION, pb
from .reference import reference as make_reference

M = TypeVar("M", bound=Message)


def _update_fields() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The single-value and the law fields of a ChannelUpdate, read from the generated
    module's descriptor (the .proto the Rust side is built from, whose optional numbers a
    Rust test holds equal to the control core's table of tunable parameters)."""
    d = pb.ChannelUpdate.DESCRIPTOR
    law = d.oneofs_by_name["law"]
    values = tuple(f.name for f in d.fields if f.type == f.TYPE_DOUBLE and f.has_presence)
    return values, tuple(f.name for f in law.fields)


#: The single-value fields of a ChannelUpdate: the tunable parameters by name (units,
#: bounds and which law has which in docs/parameters.md, or ``mfcctl params``).
#: Its law fields: a new law replacing the one in force (its output map kept).
UPDATE_FIELDS, LAW_FIELDS = _update_fields()



# A keyed service seals its error replies (protobuf field 100: a2 06 20, then 32 bytes of
# MAC): without the key they are shown without those bytes, unchecked.
_TRAILER_HEAD = b"\xa2\x06\x20"
_TRAILER_LEN = len(_TRAILER_HEAD) + 32


def _error_text(raw: bytes) -> str:
    if len(raw) >= _TRAILER_LEN and raw[-_TRAILER_LEN:-32] == _TRAILER_HEAD:
        raw = raw[:-_TRAILER_LEN]
    return raw.decode("utf-8", errors="replace")

class MfcError(Exception):
    """Any failure of a request to a controller."""


class NoReply(MfcError):
    """Nobody answered: no controller serves the key (or it is not reachable yet)."""


class ErrorReply(MfcError):
    """The controller answered with an error (e.g. a status query for a device it does not
    serve); ``text`` is its message."""

    def __init__(self, key: str, text: str) -> None:
        super().__init__(f"{key}: {text}")
        self.key = key
        self.text = text


class Refused(MfcError):
    """The controller refused a change (nothing changed); ``reason`` says why and
    ``config`` is the configuration still in force (if it sent one)."""

    def __init__(self, what: str, reason: str, config: pb.DeviceConfig | None) -> None:
        super().__init__(f"{what} refused: {reason}")
        self.reason = reason
        self.config = config


def _decode(cls: type[M], raw: bytes, key: str) -> M:
    msg = cls()
    try:
        msg.ParseFromString(raw)
    except DecodeError as e:
        raise MfcError(f"{key}: reply does not decode as {cls.__name__}: {e}") from e
    version = getattr(msg, "version")
    if version != PROTOCOL_VERSION:
        raise MfcError(f"{key}: reply has protocol version {version}, this client speaks {PROTOCOL_VERSION}")
    return msg


def limits(min: float | None = None, max: float | None = None, rate_limit: float | None = None) -> pb.ChannelLimits:
    """One channel of an envelope; None leaves that side unbounded."""
    c = pb.ChannelLimits()
    if min is not None:
        c.min = min
    if max is not None:
        c.max = max
    if rate_limit is not None:
        c.rate_limit = rate_limit
    return c


class Operator:
    """Requests to the controllers reachable through ``session``.

    Every method waits at most ``timeout`` seconds for an answer. If several controllers
    serve a device (hot standby), the first answer is taken. ``operator`` names who asks
    in every request on a device (``.../by/{operator}``): under a deployment, the common
    name of the operator's certificate; ``None`` asks as nobody, which a service with an
    access section refuses (an open one records it as ``anonymous``).
    """

    def __init__(self, session: zenoh.Session, timeout: float = 5.0, operator: str | None = None) -> None:
        self.session = session
        self.timeout = timeout
        self.operator = keys.check_id(operator) if operator is not None else None

    def _named(self, key: str) -> str:
        """``key``, naming the operator if there is one."""
        return key if self.operator is None else keys.by(key, self.operator)

    # ---- plumbing ----------------------------------------------------------------------

    def _replies(self, key: str, payload: bytes | None, timeout: float | None = None) -> list[zenoh.Reply]:
        """Every reply to a query on ``key`` (all matching queryables, none merged away)."""
        t = self.timeout if timeout is None else timeout
        target, merge = zenoh.QueryTarget.ALL, zenoh.ConsolidationMode.NONE
        if payload is None:
            # No payload at all means "read": an empty one would be a (bad) change request.
            return list(self.session.get(key, target=target, consolidation=merge, timeout=t))
        return list(self.session.get(key, target=target, consolidation=merge, timeout=t, payload=payload))

    def _ask_all(self, key: str, payload: bytes | None) -> tuple[list[bytes], list[str]]:
        """Every reply: the payloads of the good ones, the texts of the errors."""
        oks, errors = [], []
        for r in self._replies(key, payload):
            if r.ok is not None:
                oks.append(r.ok.payload.to_bytes())
            elif r.err is not None:
                errors.append(_error_text(r.err.payload.to_bytes()))
        return oks, errors

    def _ask(self, key: str, payload: bytes | None) -> bytes:
        """The payload of the first good reply; ErrorReply if there were only errors."""
        oks, errors = self._ask_all(key, payload)
        if oks:
            return oks[0]
        if errors:
            raise ErrorReply(key, "; ".join(errors))
        raise NoReply(f"{key}: no reply within {self.timeout} s (is a controller serving it?)")

    def _config_reply(self, key: str, payload: bytes | None, what: str) -> pb.ConfigReply:
        """The ConfigReply of the service that serves the device.

        Every service on the network answers a device's config, envelope and reference
        queries. One that does not serve the device answers with an error reply (older
        builds: "refused" *without* a configuration, having none), while the one that serves
        it always sends the configuration in force, accepted or not. So that answer wins,
        whatever the order; errors count only when nobody served the device.
        """
        oks, errors = self._ask_all(key, payload)
        if not oks:
            if errors:
                raise ErrorReply(key, "; ".join(errors))
            raise NoReply(f"{key}: no reply within {self.timeout} s (is a controller serving it?)")
        replies = [_decode(pb.ConfigReply, raw, key) for raw in oks]
        served = [r for r in replies if r.accepted or r.HasField("config")]
        reply = served[0] if served else replies[0]
        if not reply.accepted:
            raise Refused(what, reply.reason, reply.config if reply.HasField("config") else None)
        return reply

    # ---- configuration -----------------------------------------------------------------

    def config(self, device: str) -> pb.DeviceConfig:
        """The device's whole configuration in force (laws, output maps, reference, envelope)."""
        return self._config_reply(self._named(keys.config(device)), None, "reading the configuration").config

    def configure(self, device: str, request: pb.ConfigRequest) -> pb.DeviceConfig:
        """Send a ConfigRequest (its version is set here); the configuration after it."""
        request.version = PROTOCOL_VERSION
        return self._config_reply(
            self._named(keys.config(device)), request.SerializeToString(), "configuration change"
        ).config

    def update(self, device: str, channel: int, **fields: float | pb.Intelligent | pb.Pid | pb.Adrc) -> pb.DeviceConfig:
        """Change some fields of one channel, keeping every other value in force.

        ``fields`` are ChannelUpdate fields: gains (``kp=2.0``), output-map values
        (``max=5.0``), or a new law (``pid=pb.Pid(kp=1.0)``), applied before the single
        values. A parameter the law does not have (``alpha`` on a PID) is refused by the
        controller, naming it.
        """
        return self.updates(device, [(channel, fields)])

    def updates(self, device: str, changes: Sequence[tuple[int, dict]]) -> pb.DeviceConfig:
        """Several channel updates in one all-or-nothing request: ``[(channel, fields), ...]``."""
        req = pb.ConfigRequest(version=PROTOCOL_VERSION)
        for channel, fields in changes:
            unknown = set(fields) - set(UPDATE_FIELDS) - set(LAW_FIELDS)
            if unknown:
                raise ValueError(
                    f"unknown ChannelUpdate field(s) {sorted(unknown)}; "
                    f"use {', '.join(UPDATE_FIELDS + LAW_FIELDS)}"
                )
            u = req.updates.add(channel=channel)
            for name, value in fields.items():
                if name in LAW_FIELDS:
                    getattr(u, name).CopyFrom(value)
                else:
                    setattr(u, name, float(value))
        return self.configure(device, req)

    def set_channels(
        self, device: str, channels: Sequence[pb.ChannelConfig | pb.Intelligent | pb.Pid | pb.Adrc]
    ) -> pb.DeviceConfig:
        """Replace every channel's law (and output map, where given).

        A bare law (``pb.Pid(...)``) or a ChannelConfig without ``output`` keeps the output
        map in force; no map can leave the envelope.
        """
        req = pb.ConfigRequest(version=PROTOCOL_VERSION)
        for c in channels:
            if isinstance(c, pb.ChannelConfig):
                req.channels.append(c)
            elif isinstance(c, pb.Intelligent):
                req.channels.add(intelligent=c)
            elif isinstance(c, pb.Pid):
                req.channels.add(pid=c)
            elif isinstance(c, pb.Adrc):
                req.channels.add(adrc=c)
            else:
                raise TypeError(f"not a channel or a law: {type(c).__name__}")
        return self.configure(device, req)

    # ---- reference ---------------------------------------------------------------------

    def set_reference(
        self, device: str, channels: Sequence[Sequence[pb.Piece]], start_time: float = 0.0
    ) -> pb.DeviceConfig:
        """Replace the reference (one list of pieces per channel, see
        :mod:`mfc_client.reference`), answered: raises :class:`Refused` with the reason."""
        u = pb.ReferenceUpdate(version=PROTOCOL_VERSION, reference=make_reference(channels, start_time))
        return self._config_reply(self._named(keys.reference(device)), u.SerializeToString(), "reference").config

    def publish_reference(
        self, device: str, channels: Sequence[Sequence[pb.Piece]], start_time: float = 0.0
    ) -> None:
        """The same, published and not answered (a refusal only shows in the device's status
        as ``references_refused`` and ``last_error``): for steering at a high rate."""
        u = pb.ReferenceUpdate(version=PROTOCOL_VERSION, reference=make_reference(channels, start_time))
        self.session.put(self._named(keys.reference(device)), u.SerializeToString())

    # ---- envelope ----------------------------------------------------------------------

    def envelope(self, device: str) -> pb.Envelope:
        """The device's safety envelope in force."""
        return self._config_reply(self._named(keys.envelope(device)), None, "reading the envelope").config.envelope

    def change_envelope(
        self,
        device: str,
        channels: Sequence[tuple[float | None, float | None, float | None] | pb.ChannelLimits],
        reason: str,
    ) -> pb.Envelope:
        """Set the envelope, one ``(min, max, rate_limit)`` per channel (None: unbounded).

        Narrowing is always accepted (output maps are narrowed to fit); widening only if the
        service's file has ``allow_remote_widening``. ``reason`` goes to the service's log.
        """
        req = pb.EnvelopeRequest(version=PROTOCOL_VERSION, reason=reason)
        for c in channels:
            req.envelope.channels.append(c if isinstance(c, pb.ChannelLimits) else limits(*c))
        return self._config_reply(
            self._named(keys.envelope(device)), req.SerializeToString(), "envelope change"
        ).config.envelope

    # ---- status ------------------------------------------------------------------------

    def status(self, device: str) -> pb.DeviceStatus:
        """The device's counters and state; :class:`ErrorReply` if no controller serves it."""
        key = self._named(keys.status(device))
        return _decode(pb.DeviceStatus, self._ask(key, None), key)

    def audit(self, device: str) -> list[pb.AuditEntry]:
        """The device's latest audited changes (at most 64), oldest first: who, when, what
        moved from what to what, accepted or refused and why."""
        key = self._named(keys.audit(device))
        return list(_decode(pb.AuditLog, self._ask(key, None), key).entries)

    def service(self, controller: str) -> pb.ServiceStatus:
        """One service's status."""
        key = keys.service_status(controller)
        return _decode(pb.ServiceStatus, self._ask(key, None), key)

    def services(self, timeout: float | None = None) -> list[pb.ServiceStatus]:
        """The status of every reachable service, one each (sorted by controller id).

        The query ends when every service the network knows of has answered (or at the
        timeout, if one stays silent).
        """
        key = keys.service_status("*")
        out = []
        for r in self._replies(key, None, timeout):
            if r.ok is not None:
                out.append(_decode(pb.ServiceStatus, r.ok.payload.to_bytes(), str(r.ok.key_expr)))
        return sorted(out, key=lambda s: s.controller_id)
