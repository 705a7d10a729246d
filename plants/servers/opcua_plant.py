#!/usr/bin/env python3
"""A plant behind an OPC UA server, as a PLC would expose it: asyncua's server (not ours)
hosting one of the example plants' physics, in real time.

The physics are the example drivers' own (plants/heater/heater.py, plants/dc-motor/
dc_motor.py), advanced to the wall clock every millisecond and whenever a client reads
or writes (a Read answers with the plant as it is when the request arrives);
a write acts from the moment it arrives, its value clamped to the actuator's range, as an
actuator would.

Address space (namespace "urn:mfc:plant", index 2):
    ns=2;s=Plant.Output     Double   the measured output (degC or rad)    read-only
    ns=2;s=Plant.Input      Double   the input to apply (V)                 writable
    ns=2;s=Plant.Applied    Double   the input really applied (V)           read-only

Misbehaviour on demand, for the bridge's tests (seconds after the first write):
    --nan-after S       the output reads NaN
    --vanish-after S    the output node is deleted (reads give BadNodeIdUnknown)
    --silent-after S    the server stops answering anything (its event loop blocks)

Security (default: None, anonymous):
    --user NAME --password PW   the one user, by name
    --user-certificate FILE     the one user, by certificate (DER)
    --security P,...            asyncua's policy names (Basic256Sha256_SignAndEncrypt, ...)
    --pki DIR                   the server's certificate (DIR/own/cert.der, made with its
                                key DIR/own/key.pem if absent) and the clients it trusts:
                                the certificates in DIR/trusted/, read again at every
                                session (anything else is refused, BadCertificateUntrusted)

Usage
    opcua_plant.py --plant heater|dc-motor --port 4840 [security flags] [--seed N] [plant flags...]
    opcua_plant.py --make-certificate PREFIX   writes PREFIX.der and PREFIX.pem (a user's)
Prints `listening PORT` on stdout once it accepts connections.
"""

import argparse
import asyncio
import logging
import math
import sys
import time
from pathlib import Path

sys.dont_write_bytecode = True
from asyncua import Server, ua  # noqa: E402
from asyncua.common.callback import CallbackType  # noqa: E402

from physics import PLANTS, RealTime, load_plant  # noqa: E402

NS = "urn:mfc:plant"


SERVER_URI = "urn:mfc:plant-server"


class Users:
    """One user, by name and password or by certificate (asyncua's user manager interface)."""

    def __init__(self, name=None, password=None, certificate=None):
        self.name, self.password, self.certificate = name, password, certificate

    def get_user(self, iserver, username=None, password=None, certificate=None):
        from asyncua.crypto.permission_rules import User, UserRole

        if self.name is not None and (username, password) == (self.name, self.password):
            return User(role=UserRole.User)
        if self.certificate is not None and certificate == self.certificate:
            return User(role=UserRole.User)
        return None


def der_of(path):
    """A certificate file's DER bytes (DER or PEM on disk)."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    data = Path(path).read_bytes()
    if data.startswith(b"-----BEGIN"):
        return x509.load_pem_x509_certificate(data).public_bytes(Encoding.DER)
    return data


def trusting(directory):
    """A validator that accepts exactly the client certificates in `directory`, read again
    at each session (an operator trusts a client while the server runs)."""
    from asyncua.common.utils import ServiceError
    from cryptography.hazmat.primitives.serialization import Encoding

    async def validate(certificate, _app_description):
        der = certificate.public_bytes(Encoding.DER)
        trusted = [der_of(p) for p in sorted(Path(directory).glob("*")) if p.is_file()]
        if der not in trusted:
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)

    return validate


async def make_certificate(key, cert, uri, server):
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    use = [ExtendedKeyUsageOID.SERVER_AUTH] if server else [ExtendedKeyUsageOID.CLIENT_AUTH]
    Path(key).parent.mkdir(parents=True, exist_ok=True)
    await setup_self_signed_certificate(
        Path(key), Path(cert), uri, "127.0.0.1", use, {"commonName": uri.rsplit(":", 1)[-1]}
    )


async def secure(server, args):
    """The policies, the server's certificate and the clients it trusts."""
    policies = [getattr(ua.SecurityPolicyType, p) for p in args.security.split(",")]
    server.set_security_policy(policies)
    if args.pki:
        pki = Path(args.pki)
        (pki / "trusted").mkdir(parents=True, exist_ok=True)
        await make_certificate(pki / "own/key.pem", pki / "own/cert.der", SERVER_URI, server=True)
        await server.load_certificate(str(pki / "own/cert.der"))
        await server.load_private_key(str(pki / "own/key.pem"))
        server.set_certificate_validator(trusting(pki / "trusted"))
    tokens = []
    if args.user:
        tokens.append(ua.UserNameIdentityToken)
    if args.user_certificate:
        tokens.append(ua.X509IdentityToken)
    if tokens:
        server.set_identity_tokens(tokens)


async def serve(args, plant_argv):
    rt = RealTime(load_plant(args.plant, plant_argv), args)
    user_cert = der_of(args.user_certificate) if args.user_certificate else None
    users = Users(args.user, args.password, user_cert) if args.user or user_cert else None
    server = Server(user_manager=users)
    await server.init()
    server.set_endpoint(f"opc.tcp://{args.host}:{args.port}/")
    await server.set_application_uri(SERVER_URI)
    await secure(server, args)
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
    published = {"applied": 0.0}  # the node's initial value

    async def publish():
        """The plant as it is now into the address space."""
        nonlocal vanished
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
        if rt.applied != published["applied"]:
            # Only on a change: every write costs asyncua's data-change machinery, and the
            # server's CPU is what a busy host's subscribers wait on.
            published["applied"] = rt.applied
            await server.write_attribute_value(
                applied.nodeid, ua.DataValue(ua.Variant(float(rt.applied), ua.VariantType.Double))
            )

    async def on_read(event, _dispatcher):
        # A Read answers with the plant as it is when the request arrives (as the Modbus
        # server does, and a PLC's process image nearly does), not as the 1 ms loop below
        # last left it: that loop shares the event loop with the requests, and on a busy
        # host its "1 ms" stretched to several, a value of random age that no client's
        # timing could account for.
        read = {rv.NodeId for rv in event.request_params.NodesToRead}
        if output.nodeid in read or applied.nodeid in read:
            await publish()

    server.subscribe_server_callback(CallbackType.PreRead, on_read)
    async with server:
        print(f"listening {args.port}", flush=True)
        while True:
            # Subscriptions see the values this loop writes (their data changes).
            await publish()
            await asyncio.sleep(0.001)


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--plant", choices=sorted(PLANTS), required=True)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=4840)
    p.add_argument("--user")
    p.add_argument("--password")
    p.add_argument("--user-certificate")
    p.add_argument("--security", default="NoSecurity")
    p.add_argument("--pki")
    p.add_argument("--nan-after", type=float)
    p.add_argument("--vanish-after", type=float)
    p.add_argument("--silent-after", type=float)
    return p.parse_known_args(argv)


def main(argv=None):
    logging.basicConfig(level=logging.ERROR)
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--make-certificate"] and len(argv) == 2:
        prefix = argv[1]
        asyncio.run(make_certificate(prefix + ".pem", prefix + ".der", "urn:mfc:user", server=False))
        return 0
    args, plant_argv = parse_args(argv)
    try:
        asyncio.run(serve(args, plant_argv))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
