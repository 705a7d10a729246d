"""The key-expression layout (mirrors ``protocol/src/keys.rs``).

The protocol version is in the prefix, so two incompatible generations never exchange a
byte. Device and controller ids are single key chunks.
"""

from __future__ import annotations

import re

#: Prefix of every key of this protocol version.
PREFIX = "mfc/v1"

_ID = re.compile(r"[A-Za-z0-9_.\-]{1,64}")


def check_id(id_: str) -> str:
    """Return ``id_`` if it can be a device or controller id, else raise ``ValueError``.

    Checked on the client so that a typo fails here, with a message, rather than as a
    query nobody answers (an id with ``/`` or ``*`` would address other keys).
    """
    if not _ID.fullmatch(id_):
        raise ValueError(f"invalid id {id_!r}: use 1 to 64 letters, digits, '-', '_' or '.'")
    return id_


def sample(device: str) -> str:
    """``mfc/v1/device/{id}/sample``: plant -> controller, a Sample every period."""
    return f"{PREFIX}/device/{check_id(device)}/sample"


def command(device: str) -> str:
    """``mfc/v1/device/{id}/command``: controller -> plant, the Command answering a sample."""
    return f"{PREFIX}/device/{check_id(device)}/command"


def config(device: str) -> str:
    """``mfc/v1/device/{id}/config``: queryable, read (empty) or change (ConfigRequest)."""
    return f"{PREFIX}/device/{check_id(device)}/config"


def envelope(device: str) -> str:
    """``mfc/v1/device/{id}/envelope``: queryable, read (empty) or change (EnvelopeRequest)."""
    return f"{PREFIX}/device/{check_id(device)}/envelope"


def reference(device: str) -> str:
    """``mfc/v1/device/{id}/reference``: put or query a ReferenceUpdate."""
    return f"{PREFIX}/device/{check_id(device)}/reference"


def status(device: str) -> str:
    """``mfc/v1/device/{id}/status``: queryable, a DeviceStatus."""
    return f"{PREFIX}/device/{check_id(device)}/status"


def audit(device: str) -> str:
    """``mfc/v1/device/{id}/audit``: queryable, an AuditLog (the device's latest changes)."""
    return f"{PREFIX}/device/{check_id(device)}/audit"


def by(key: str, operator: str) -> str:
    """``{key}/by/{operator}``: a request on a device's key naming its operator. Under a
    deployment the router lets an operator's certificate use its own name only; a service
    with an access section refuses requests that name nobody."""
    return f"{key}/by/{check_id(operator)}"


def service_status(controller: str = "*") -> str:
    """``mfc/v1/service/{controller}/status``; ``*`` asks every service (one reply each)."""
    if controller != "*":
        check_id(controller)
    return f"{PREFIX}/service/{controller}/status"


def alive_controller(controller: str = "*") -> str:
    """``mfc/v1/alive/controller/{controller}``: a controller's liveliness token."""
    if controller != "*":
        check_id(controller)
    return f"{PREFIX}/alive/controller/{controller}"


def alive_plant(device: str) -> str:
    """``mfc/v1/alive/plant/{id}``: a plant agent's liveliness token."""
    return f"{PREFIX}/alive/plant/{check_id(device)}"
