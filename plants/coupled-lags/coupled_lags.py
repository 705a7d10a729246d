#!/usr/bin/env python3
"""N coupled first-order lags: a generic N-channel test and example plant.

A plant driver for the agent's driver protocol (see plant-agent/DRIVER.md and
plants/README.md): one ASCII line each way over stdin/stdout, time passes only through
`advance`. N channels (`--channels`, 1 ..= 64, default 3).

Plant, for channels i = 0 .. N-1 (the driver's order; channel 0 is the first number)
    tau_i * dy_i/dt = -y_i + b_i * v_i + c * sum_{j != i} y_j / (N - 1)

    y_i    output i (dimensionless; starts at 0)
    v_i    input i, actuator range -10 .. 10 (clamped)
    b_i    input gain        = 1.0 + 0.1 * i          (1.0, 1.1, 1.2, ...)
    tau_i  time constant, s  = 0.5 + 0.25 * i         (0.5, 0.75, 1.0, ...)
    c      coupling          --coupling (default 0.2): each output is pushed by the mean of
                             the others. |c| < 1 keeps the plant stable. With N = 1 there is
                             nothing to couple to and the term vanishes.

    Static gain of channel i alone (the others at 0): b_i, up to the coupling; with all
    inputs equal to u the steady state solves (1 + c/(N-1)) y_i - c/(N-1) sum_j y_j = b_i u.
    Near-step slope: dy_i/dt = b_i / tau_i per unit input (2.0, 1.47, 1.2, ... /s).

Measurement
    y_i + Gaussian noise of std `--noise` (default 0.001) per channel and per read (Box-Muller
    on random.Random(--seed)): the same seed and the same requests give the same answers.

Integration
    Classic RK4 with a fixed 10 ms sub-step (50 steps per fastest time constant); an
    `advance` that is not a multiple of it ends with one shorter step, so any DT (including
    0) is integrated to the same accuracy. The inputs are held between writes. At most
    60 s per `advance` (split longer waits), as for every driver (plants/driver_loop.py).

Protocol (one answer per request, flushed; the loop and its limits are plants/driver_loop.py)
    (start)            -> hello channels=N
    read               -> y_0 ... y_{N-1}
    write v_0 .. v_N-1 -> ok a_0 ... a_{N-1}   (a = v clamped to -10 .. 10)
    advance DT         -> ok                   (0 <= DT <= 60 and finite, seconds)
    stop               -> ok, all inputs 0, exit 0
    end of stdin       -> all inputs 0, exit 0
    anything else      -> err MESSAGE (nothing changes)

Try it by hand
    printf 'read\\nwrite 1 0 -1\\nadvance 1\\nread\\nadvance 5\\nread\\nstop\\n' | python3 coupled_lags.py
    printf 'write 1\\nadvance 3\\nread\\nstop\\n' | python3 coupled_lags.py --channels 1 --noise 0
"""

import argparse
import math
import os
import random
import sys
from math import cos, log, sin, sqrt

# The serve loop, shared by the drivers: plants/driver_loop.py, found from this file's place
# so that the driver runs from any working directory (bytecode is not written into the tree).
sys.dont_write_bytecode = True
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir))
from driver_loop import MAX_CHANNELS, run  # noqa: E402

U_MIN = -10.0
U_MAX = 10.0
SUBSTEP = 0.01  # s
TWO_PI = 2.0 * math.pi


class CoupledLags:
    """N first-order lags coupled through the mean of the other outputs; RK4."""

    def __init__(self, n, coupling, noise, seed):
        self.n = n
        self.noise = noise
        self.rng = random.Random(seed)
        self.y = [0.0] * n
        self.applied = [0.0] * n
        self.inv_tau = [1.0 / (0.5 + 0.25 * i) for i in range(n)]
        self.gain = [1.0 + 0.1 * i for i in range(n)]
        # dy_i/dt = (-(1 + k) y_i + k * S + b_i v_i) / tau_i,  S = sum_j y_j,  k = c / (N-1)
        k = coupling / (n - 1) if n > 1 else 0.0
        self.k = k
        self.self_gain = 1.0 + k
        self._set_forcing()

    def _set_forcing(self):
        self.forcing = [b * v for b, v in zip(self.gain, self.applied)]

    def read(self):
        if self.noise > 0.0:
            return [y + e for y, e in zip(self.y, self._normals())]
        return self.y

    def _normals(self):
        """N Gaussian samples of std `noise`: Box-Muller on pairs of rng.random(), both
        outputs used (random.gauss costs about 1 us a sample, too much for 64 channels)."""
        r = self.rng.random
        s = self.noise
        out = []
        for _ in range((self.n + 1) // 2):
            rad = s * sqrt(-2.0 * log(1.0 - r()))  # 1 - random() is in (0, 1]
            ang = TWO_PI * r()
            out.append(rad * cos(ang))
            out.append(rad * sin(ang))
        return out

    def write(self, values):
        a = [U_MIN if v < U_MIN else U_MAX if v > U_MAX else v for v in values]
        self.applied = a
        self._set_forcing()
        return a

    def _rk4(self, h):
        """One classic RK4 step of h seconds. The coupling only needs the sum of a stage's
        state, sum(y + c k) = sum(y) + c sum(k), so each stage is a single pass."""
        y = self.y
        f = self.forcing
        it = self.inv_tau
        k = self.k
        m = self.self_gain
        hh = 0.5 * h
        sy = sum(y)
        s = k * sy
        k1 = [(s - m * a + b) * c for a, b, c in zip(y, f, it)]
        s = k * (sy + hh * sum(k1))
        k2 = [(s - m * (a + hh * d) + b) * c for a, d, b, c in zip(y, k1, f, it)]
        s = k * (sy + hh * sum(k2))
        k3 = [(s - m * (a + hh * d) + b) * c for a, d, b, c in zip(y, k2, f, it)]
        s = k * (sy + h * sum(k3))
        k4 = [(s - m * (a + h * d) + b) * c for a, d, b, c in zip(y, k3, f, it)]
        h6 = h / 6.0
        self.y = [a + h6 * (p + 2.0 * (q + r) + w) for a, p, q, r, w in zip(y, k1, k2, k3, k4)]

    def advance(self, dt):
        steps = int(dt / SUBSTEP)
        rest = dt - steps * SUBSTEP
        for _ in range(steps):
            self._rk4(SUBSTEP)
        if rest > 1e-12 * SUBSTEP:
            self._rk4(rest)

    def safe_stop(self):
        self.write([0.0] * self.n)


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="N coupled first-order lags, a driver for the agent's line protocol."
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the measurement noise (default 0)")
    p.add_argument("--channels", type=int, default=3, help=f"N, 1 ..= {MAX_CHANNELS} (default 3)")
    p.add_argument("--coupling", type=float, default=0.2, help="coupling c (default 0.2)")
    p.add_argument("--noise", type=float, default=0.001, help="measurement noise std (default 0.001)")
    a = p.parse_args(argv)
    if not 1 <= a.channels <= MAX_CHANNELS:
        p.error(f"--channels must be in 1 ..= {MAX_CHANNELS}")
    if not math.isfinite(a.coupling):
        p.error("--coupling must be finite")
    if not (math.isfinite(a.noise) and a.noise >= 0.0):
        p.error("--noise must be finite and >= 0")
    return a


def main(argv=None):
    args = parse_args(argv)
    return run(CoupledLags(args.channels, args.coupling, args.noise, args.seed), args.channels)


if __name__ == "__main__":
    sys.exit(main())
