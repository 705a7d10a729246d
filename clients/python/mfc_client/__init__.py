"""Python client of the model-free control service over Zenoh (protocol ``mfc.v1``).

* :func:`connect` opens a zenoh session as the Rust binaries do;
* :class:`PlantLink` is a plant's end of the loop (samples out, commands in);
* :class:`Operator` reads and changes configuration, envelope, reference and status;
* :mod:`mfc_client.reference` builds reference pieces;
* :mod:`mfc_client.auth` seals and checks messages for a deployment with keys;
* ``pb`` is the generated protobuf module (``mfc/v1/mfc.proto``), ``keys`` the key layout.

Run ``clients/python/setup.sh`` first: it makes the venv and generates ``pb``.
"""

from . import auth, keys, reference
from ._pb import MAX_PAYLOAD, PROTOCOL_VERSION, pb
from .operator import ErrorReply, MfcError, NoReply, Operator, Refused, limits
from .plant import LinkStats, PlantLink, RunStats, new_run_id
from .session import connect, controllers, wait_for_controller

__all__ = [
    "MAX_PAYLOAD",
    "PROTOCOL_VERSION",
    "ErrorReply",
    "LinkStats",
    "MfcError",
    "NoReply",
    "Operator",
    "PlantLink",
    "Refused",
    "RunStats",
    "connect",
    "auth",
    "controllers",
    "keys",
    "limits",
    "new_run_id",
    "pb",
    "reference",
    "wait_for_controller",
]
