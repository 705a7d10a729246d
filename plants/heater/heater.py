#!/usr/bin/env python3
"""Electric heater with a temperature sensor: a first-order process with dead time (FOPDT).

A plant driver for the agent's driver protocol (see plant-agent/DRIVER.md and
plants/README.md): one ASCII line each way over stdin/stdout, time passes only through
`advance`. One channel.

Plant
    tau * dT/dt = -(T - T_amb) + K * v(t - L)

    T      temperature of the heated body, degC (the output; starts at T_amb)
    v      heater voltage, V (the input), actuator range 0 .. 24 V: clamped, a heater
           cannot cool, so the range is one-sided
    T_amb  ambient temperature, degC         --ambient    (default 20)
    K      static gain, degC per V           --gain       (default 2.5)
    tau    time constant, s                  --tau        (default 20)
    L      dead time (transport delay), s    --dead-time  (default 2.0)

    Static map: T = T_amb + K * v, e.g. 10 V -> 45 degC. Near-step slope after the dead
    time: K / tau = 0.125 degC/s per V.

Measurement
    T + Gaussian noise of std `--noise` degC (default 0.05), quantised to 0.01 degC. The
    noise comes from random.Random(--seed): the same seed and the same requests give the
    same answers.

Integration
    The input is held between writes and the dead time only shifts it, so the delayed input
    is piecewise constant with switching times (write time + L). Between switches the
    equation is solved exactly (T -> T_inf + (T - T_inf) * exp(-h / tau)), so an `advance`
    of any length (0, irregular, not a multiple of anything) is exact to rounding. The dead
    time is a time-stamped history of the applied inputs (not a queue of samples), so it
    does not depend on how the agent slices time.

Protocol (one answer per request, flushed; the loop and its limits are plants/driver_loop.py)
    (start)          -> hello channels=1
    read             -> T                    (degC)
    write v          -> ok a                 (a = v clamped to 0 .. 24 V)
    advance DT       -> ok                   (0 <= DT <= 60 and finite, seconds)
    stop             -> ok, heater off (0 V), exit 0
    end of stdin     -> heater off, exit 0
    anything else    -> err MESSAGE (nothing changes)

Try it by hand
    printf 'read\\nwrite 12\\nadvance 1\\nread\\nadvance 5\\nread\\nstop\\n' | python3 heater.py
    python3 heater.py --seed 3 --gain 2.0 --ambient 15 --noise 0
"""

import argparse
import math
import os
import random
import sys
from collections import deque

# The serve loop, shared by the drivers: plants/driver_loop.py, found from this file's place
# so that the driver runs from any working directory (bytecode is not written into the tree).
sys.dont_write_bytecode = True
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir))
from driver_loop import run  # noqa: E402

V_MIN = 0.0  # V: the heater cannot cool
V_MAX = 24.0  # V


class Heater:
    """The FOPDT plant, integrated exactly between input switches."""

    def __init__(self, ambient, gain, tau, dead_time, noise, seed):
        self.ambient = ambient
        self.gain = gain
        self.tau = tau
        self.dead_time = dead_time
        self.noise = noise
        self.rng = random.Random(seed)
        self.t = 0.0  # plant time, s
        self.temp = ambient  # degC
        self.applied = 0.0  # V, the input applied now (after clamping)
        self.delayed = 0.0  # V, the input acting on the plant now: v(t - L)
        # Pending switches of the delayed input: (time it starts acting, volts), in time order.
        self.pending = deque()

    def read(self):
        y = self.temp
        if self.noise > 0.0:
            y += self.rng.gauss(0.0, self.noise)
        # Quantise to 0.01 degC; k / 100 is the double nearest the decimal (prints as 45.03).
        return [round(y * 100.0) / 100.0]

    def write(self, values):
        (v,) = values
        a = V_MIN if v < V_MIN else V_MAX if v > V_MAX else v
        if a != self.applied:
            self.applied = a
            at = self.t + self.dead_time
            pending = self.pending
            if pending and pending[-1][0] >= at:
                # Several writes at the same instant: the last one wins.
                pending.pop()
            pending.append((at, a))
        return [a]

    def _evolve(self, h):
        """Exact solution over h seconds with the delayed input held."""
        if h > 0.0:
            target = self.ambient + self.gain * self.delayed
            self.temp = target + (self.temp - target) * math.exp(-h / self.tau)

    def advance(self, dt):
        end = self.t + dt
        pending = self.pending
        while pending and pending[0][0] <= end:
            at, v = pending.popleft()
            self._evolve(at - self.t)
            if at > self.t:
                self.t = at
            self.delayed = v
        self._evolve(end - self.t)
        self.t = end

    def safe_stop(self):
        self.write([0.0])


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="Heater with dead time (FOPDT), a driver for the agent's line protocol."
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the measurement noise (default 0)")
    p.add_argument("--ambient", type=float, default=20.0, help="ambient temperature, degC (default 20)")
    p.add_argument("--gain", type=float, default=2.5, help="static gain K, degC/V (default 2.5)")
    p.add_argument("--tau", type=float, default=20.0, help="time constant, s (default 20)")
    p.add_argument("--dead-time", type=float, default=2.0, help="dead time L, s (default 2.0)")
    p.add_argument("--noise", type=float, default=0.05, help="measurement noise std, degC (default 0.05)")
    a = p.parse_args(argv)
    for name in ("ambient", "gain", "tau", "dead_time", "noise"):
        if not math.isfinite(getattr(a, name)):
            p.error(f"--{name.replace('_', '-')} must be finite")
    if a.tau <= 0.0:
        p.error("--tau must be > 0")
    if a.dead_time < 0.0:
        p.error("--dead-time must be >= 0")
    if a.noise < 0.0:
        p.error("--noise must be >= 0")
    return a


def main(argv=None):
    args = parse_args(argv)
    return run(Heater(args.ambient, args.gain, args.tau, args.dead_time, args.noise, args.seed), 1)


if __name__ == "__main__":
    sys.exit(main())
