#!/usr/bin/env python3
"""A first-order lag simulated in Python, controlled by a controller-service over Zenoh.

    dy/dt = (-y + k v) / tau

Run the service with ``examples/service.toml``, then, with the venv's python::

    python examples/first_order_plant.py --connect tcp/127.0.0.1:7447 --device py-1 --seconds 10

It reads the device's configuration first (its channel count, and its reference, to measure
the tracking error itself), runs the loop at ``--rate`` Hz on absolute deadlines, and prints
the tracking RMS and how many commands arrived, by mode. Exit status 1 if no command put the
plant under control.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mfc_client as mc  # noqa: E402
from mfc_client.reference import evaluate  # noqa: E402


class FirstOrderLag:
    """``y' = (-y + k v) / tau``, integrated exactly over a period with ``v`` held (zero-order
    hold, as a real actuator applies it)."""

    def __init__(self, k: float, tau: float, y0: float = 0.0) -> None:
        self.k, self.tau, self.y = k, tau, y0

    def advance(self, v: float, dt: float) -> float:
        a = math.exp(-dt / self.tau)
        self.y = a * self.y + (1.0 - a) * self.k * v
        return self.y


def main() -> int:
    ap = argparse.ArgumentParser(description="first-order lag plant against a controller-service")
    ap.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                    help="zenoh endpoint of the service (repeatable); default tcp/127.0.0.1:7447")
    ap.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    ap.add_argument("--mode", default="peer", choices=["peer", "client"])
    ap.add_argument("--device", default="py-1")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=100.0, help="samples per second (Hz)")
    ap.add_argument("--k", type=float, default=2.0, help="static gain (plant units per volt)")
    ap.add_argument("--tau", type=float, default=0.5, help="time constant (s)")
    ap.add_argument("--wait", type=float, default=10.0, help="how long to wait for a controller (s)")
    args = ap.parse_args()
    connect = args.connect or ([] if args.listen else ["tcp/127.0.0.1:7447"])

    session = mc.connect(connect=connect, listen=args.listen, mode=args.mode)
    try:
        if not mc.wait_for_controller(session, "*", args.wait):
            print(f"no controller reachable through {connect + args.listen} within {args.wait} s",
                  file=sys.stderr)
            return 2
        op = mc.Operator(session)
        try:
            cfg = op.config(args.device)
        except mc.MfcError as e:
            print(f"cannot read the configuration of {args.device}: {e}", file=sys.stderr)
            return 2
        if len(cfg.channels) != 1:
            print(f"{args.device} has {len(cfg.channels)} channels; this plant has one", file=sys.stderr)
            return 2

        plant = FirstOrderLag(args.k, args.tau)
        errors: list[float] = []

        def step(t: float, dt: float, v: Sequence[float]) -> list[float]:
            if dt > 0:
                plant.advance(v[0], dt)
            errors.append(plant.y - evaluate(cfg.reference, t)[0])
            return [plant.y]

        period = 1.0 / args.rate
        steps = int(round(args.seconds * args.rate))
        with mc.PlantLink(session, args.device) as link:
            stats = link.run(period, steps, step)
    finally:
        session.close()

    rms = math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else float("nan")
    rtt = sorted(stats.rtt_us)
    p50 = statistics.median(rtt) if rtt else float("nan")
    p99 = rtt[min(len(rtt) - 1, int(0.99 * len(rtt)))] if rtt else float("nan")
    print(f"{args.device}: {stats.steps} periods at {args.rate:g} Hz, "
          f"k = {args.k:g}, tau = {args.tau:g} s, run id {link.run_id:#x}")
    print(f"  commands: {stats.answered} arrived in time ({stats.control} control, "
          f"{stats.warming_up} warming up, {stats.rejected} rejected, {stats.stale} stale), "
          f"{stats.missing} missing or late")
    print(f"  tracking: rms {rms:.4g}, max |e| {max(map(abs, errors)):.4g} (plant units)")
    print(f"  round trip: p50 {p50:.0f} us, p99 {p99:.0f} us; overruns {stats.overruns}")
    if stats.last_error:
        print(f"  last refusal: {stats.last_error}")
    return 0 if stats.control > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
