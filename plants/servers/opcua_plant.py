#!/usr/bin/env python3
"""A plant behind an OPC UA server, as a PLC would expose it: asyncua's server (not ours)
hosting one of the example plants' physics, in real time.

The physics are the example drivers' own (plants/heater/heater.py, plants/dc-motor/
dc_motor.py), advanced to the wall clock every millisecond and whenever a client writes;
a write acts from the moment it arrives, its value clamped to the actuator's range, as an
actuator would.

Address space (namespace "urn:mfc:plant", index 2; security None, anonymous or user/password):
    ns=2;s=Plant.Output     Double   the measured output (degC or rad)    read-only
    ns=2;s=Plant.Input      Double   the input to apply (V)                 writable
    ns=2;s=Plant.Applied    Double   the input really applied (V)           read-only

Misbehaviour on demand, for the bridge's tests (seconds after the first write):
    --nan-after S       the output reads NaN
    --vanish-after S    the output node is deleted (reads give BadNodeIdUnknown)
    --silent-after S    the server stops answering anything (its event loop blocks)

Usage
    opcua_plant.py --plant heater|dc-motor --port 4840 [--user NAME --password PW] [--seed N] [plant flags...]
Prints `listening PORT` on stdout once it accepts connections.
"""

import argparse
import asyncio
import logging
import math
import sys
import time

sys.dont_write_bytecode = True
from asyncua import Server, ua  # noqa: E402
from asyncua.common.callback import CallbackType  # noqa: E402

from physics import PLANTS, RealTime, load_plant  # noqa: E402

NS = "urn:mfc:plant"


class Users:
    """One user with a password (asyncua's user manager interface)."""

    def __init__(self, name, password):
        self.name, self.password = name, password

    def get_user(self, iserver, username=None, password=None, certificate=None):
        from asyncua.crypto.permission_rules import User, UserRole

        if (username, password) == (self.name, self.password):
            return User(role=UserRole.User)
        return None


async def serve(args, plant_argv):
    rt = RealTime(load_plant(args.plant, plant_argv), args)
    server = Server(user_manager=Users(args.user, args.password) if args.user else None)
    await server.init()
    server.set_endpoint(f"opc.tcp://{args.host}:{args.port}/")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    if args.user:
        server.set_identity_tokens([ua.UserNameIdentityToken])
    idx = await server.register_namespace(NS)
    obj = await server.nodes.objects.add_object(f"ns={idx};s=Plant", f"{idx}:Plant")
    output = await obj.add_variable(f"ns={idx};s=Plant.Output", f"{idx}:Output", 0.0, ua.VariantType.Double)
    inp = await obj.add_variable(f"ns={idx};s=Plant.Input", f"{idx}:Input", 0.0, ua.VariantType.Double)
    applied = await obj.add_variable(f"ns={idx};s=Plant.Applied", f"{idx}:Applied", 0.0, ua.VariantType.Double)
    await inp.set_writable()

    def on_write(event, _dispatcher):
        for wv, status in zip(event.request_params.NodesToWrite, event.response_params):
            if wv.NodeId == inp.nodeid and status.is_good():
                v = float(wv.Value.Value.Value)
                if math.isfinite(v):
                    rt.apply(v)

    server.subscribe_server_callback(CallbackType.PostWrite, on_write)
    vanished = False
    async with server:
        print(f"listening {args.port}", flush=True)
        while True:
            rt.catch_up()
            if rt.misbehaving("silent_after"):
                time.sleep(3600)  # blocks the event loop: nothing is answered any more
            if rt.misbehaving("vanish_after") and not vanished:
                await server.delete_nodes([output])
                vanished = True
            if not vanished:
                (y,) = rt.plant.read()
                if rt.misbehaving("nan_after"):
                    y = float("nan")
                await server.write_attribute_value(output.nodeid, ua.DataValue(ua.Variant(float(y), ua.VariantType.Double)))
            await server.write_attribute_value(
                applied.nodeid, ua.DataValue(ua.Variant(float(rt.applied), ua.VariantType.Double))
            )
            await asyncio.sleep(0.001)


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--plant", choices=sorted(PLANTS), required=True)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=4840)
    p.add_argument("--user")
    p.add_argument("--password")
    p.add_argument("--nan-after", type=float)
    p.add_argument("--vanish-after", type=float)
    p.add_argument("--silent-after", type=float)
    return p.parse_known_args(argv)


def main(argv=None):
    logging.basicConfig(level=logging.ERROR)
    args, plant_argv = parse_args(argv)
    try:
        asyncio.run(serve(args, plant_argv))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
