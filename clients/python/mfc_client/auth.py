"""Proof of origin, as ``protocol::auth`` (Rust) defines it: HMAC-SHA256 appended to a
message as its ``mac`` field (number 100), over a label naming the message's kind and every
byte before the field.

A plant holds its own key (``mfc-deploy`` writes ``ID.auth``: 64 hexadecimal digits); the
services hold the fleet's secret, from which every device's key derives
(:func:`device_key`). A controller with keys drops an unsealed sample unread (counted as
``forged`` in its status); a :class:`~mfc_client.PlantLink` with a key drops an unsealed
or altered command the same way (counted in ``stats.forged``).
"""

from __future__ import annotations

import hashlib
import hmac
from pathlib import Path

MAC_LEN = 32
#: The field's key (100, length-delimited) and its length, as protobuf writes them.
TRAILER_HEAD = bytes([0xA2, 0x06, MAC_LEN])

SAMPLE = b"mfc/v1/sample\0"
COMMAND = b"mfc/v1/command\0"


def read_key(path: str | Path) -> bytes:
    """A key file's 32 bytes (64 hexadecimal digits, white space around ignored)."""
    text = Path(path).read_text().strip()
    key = bytes.fromhex(text)
    if len(key) != 32:
        raise ValueError(f"{path}: a key is 64 hexadecimal digits, got {len(text)} characters")
    return key


def device_key(secret: bytes, device_id: str) -> bytes:
    """Device ``device_id``'s key from the fleet's secret (what ``mfc-deploy`` writes)."""
    return hmac.new(secret, b"mfc/v1/device-key\0" + device_id.encode(), hashlib.sha256).digest()


def seal(key: bytes, label: bytes, body: bytes) -> bytes:
    """``body`` (an encoded message with an empty ``mac``) with its ``mac`` field appended."""
    tag = hmac.new(key, label + body, hashlib.sha256).digest()
    return body + TRAILER_HEAD + tag


def open_sealed(key: bytes, label: bytes, sealed: bytes) -> bytes | None:
    """The body of a sealed message if its MAC is ``key``'s (constant-time), else None."""
    if len(sealed) < len(TRAILER_HEAD) + MAC_LEN:
        return None
    body, head, tag = sealed[:-35], sealed[-35:-32], sealed[-32:]
    if head != TRAILER_HEAD:
        return None
    want = hmac.new(key, label + body, hashlib.sha256).digest()
    return body if hmac.compare_digest(want, tag) else None
