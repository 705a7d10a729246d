"""Opening a Zenoh session the way the Rust binaries do (``transport::ZenohArgs``)."""

from __future__ import annotations

import json
import time
from collections.abc import Iterable

import zenoh

from . import keys


def connect(
    connect: Iterable[str] = (),
    listen: Iterable[str] = (),
    mode: str = "peer",
    *,
    config_file: str | None = None,
    multicast_scouting: bool | None = None,
) -> zenoh.Session:
    """Open a session: peer by default, to ``connect`` endpoints, listening on ``listen``.

    With explicit endpoints multicast scouting is turned off (unless asked for): on a shared
    network it would join whatever other sessions it finds, which is how tests and demos
    end up talking to each other. Connecting never fails because the other side is not up
    yet: zenoh keeps retrying (from 0.2 s, backing off to 2 s), so the start order of plant,
    controller and operator does not matter. A peer returns at once and connects in the
    background; a client blocks here until its router (or a peer) answers.

    Args:
        connect: endpoints to connect to, e.g. ``tcp/127.0.0.1:7447``.
        listen: endpoints to listen on.
        mode: ``peer``, ``client`` or ``router``.
        config_file: a zenoh json5 file, applied first; the arguments override it.
        multicast_scouting: force scouting on or off; by default off iff endpoints are given.
    """
    connect, listen = list(connect), list(listen)
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"mode {mode!r}: use peer, client or router")
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(connect))
        # Never give up on an endpoint: a peer opens at once and connects in the background;
        # a client (which needs its router) waits in open() until one answers.
        config.insert_json5("connect/exit_on_failure", "false")
        config.insert_json5("connect/timeout_ms", "-1")
        config.insert_json5(
            "connect/retry",
            json.dumps({"period_init_ms": 200, "period_max_ms": 2000, "period_increase_factor": 2}),
        )
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if multicast_scouting is None:
        multicast_scouting = not (connect or listen)
    config.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    return zenoh.open(config)


def controllers(session: zenoh.Session, timeout: float = 1.0) -> list[str]:
    """Ids of the controllers whose liveliness token is visible now."""
    found = []
    prefix = f"{keys.PREFIX}/alive/controller/"
    for reply in session.liveliness().get(keys.alive_controller("*"), timeout=timeout):
        if reply.ok is not None:
            key = str(reply.ok.key_expr)
            found.append(key[len(prefix):] if key.startswith(prefix) else key)
    return sorted(set(found))


def wait_for_controller(
    session: zenoh.Session, controller: str = "*", timeout: float = 10.0
) -> bool:
    """Wait until the liveliness token of ``controller`` (any, with ``*``) is visible.

    The token is declared once the service's subscribers and queryables are in place, so
    after this a sample or a query reaches it (the connection may need a moment to come up,
    hence polling rather than a single look).
    """
    deadline = time.monotonic() + timeout
    key = keys.alive_controller(controller)
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        for reply in session.liveliness().get(key, timeout=min(1.0, left)):
            if reply.ok is not None:
                return True
        time.sleep(min(0.1, max(0.0, deadline - time.monotonic())))
