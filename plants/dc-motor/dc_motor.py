#!/usr/bin/env python3
"""DC motor with Coulomb friction and a backlash gear, position control of the load.

A plant driver for the agent's driver protocol (see plant-agent/DRIVER.md and
plants/README.md): one ASCII line each way over stdin/stdout, time passes only through
`advance`. One channel: input the armature voltage, output the load angle.

Plant (SI units: rad, rad/s, N m, V, A, ohm, kg m^2)
    motor      J   dw_m/dt = Kt i - b w_m - Tc sign(w_m) - tau_c        dtheta_m/dt = w_m
    armature   i = (v - Ke w_m) / R          (quasi-static: the inductance is neglected)
    load       J_L dw_L/dt = tau_c - b_L w_L - Tc_L sign(w_L)            dtheta_L/dt = w_L
    backlash   d = theta_m - theta_L, total play 2 delta (the motor starts centred in it):
                 |d| <= delta  ->  tau_c = 0                  (no contact: the load coasts)
                 d  >  delta   ->  tau_c = max(0, k_s (d - delta) + c_s (w_m - w_L))
                 d  < -delta   ->  tau_c = min(0, k_s (d + delta) + c_s (w_m - w_L))
               a dead-zone spring with contact damping; the clamp keeps the contact from
               pulling (flanks push, they do not stick).
    stiction   Coulomb friction is applied implicitly, as a bounded impulse per sub-step:
               a stopped motor stays stopped while |Kt i - b w_m - tau_c| <= Tc, and a
               motor that slows through zero stops there instead of chattering around it.
               The load's own (smaller) Coulomb friction Tc_L is treated the same way. It
               is what makes a real load stop when it is no longer driven: with viscous
               friction alone (J_L / b_L = 2 s) the load would coast across the play and hit
               the opposite flank at every deceleration, and would never wait on a
               reversal. `--load-coulomb 0` gives the purely viscous load.

    parameter                        flag                default
    v    input range                 (fixed)             -12 .. 12 V, clamped
    J    motor inertia               --inertia           2e-5 kg m^2
    J_L  load inertia                --load-inertia      1e-4 kg m^2
    Kt   torque constant             --kt                0.05 N m/A
    Ke   back-EMF constant           --ke                0.05 V s/rad
    R    armature resistance         --resistance        2 ohm
    b    motor viscous friction      --viscous           1e-5 N m s/rad
    b_L  load viscous friction       --load-viscous      5e-5 N m s/rad
    Tc   motor Coulomb friction      --coulomb           0.01 N m
    Tc_L load Coulomb friction       --load-coulomb      0.002 N m
    delta  half the backlash         --backlash          0.01 rad (total play 0.02 rad)
    k_s  gear/shaft stiffness        --stiffness         50 N m/rad
    c_s  contact damping             --contact-damping   0.03 N m s/rad
         encoder resolution          --counts            2048 counts/rev (on the load)
         extra angle noise std       --noise             0 rad (added before quantising)
         integration sub-step        --substep           2e-4 s

    Derived figures (defaults): the motor breaks away at Tc R / Kt = 0.4 V (it then
    crosses the play and stalls against the load), motor and load together at
    (Tc + Tc_L) R / Kt = 0.48 V; steady speed at 3 V
    (Kt v/R - Tc - Tc_L) / (Kt Ke/R + b + b_L) ~ 48 rad/s; mechanical time constant
    (J + J_L) / (Kt Ke/R + b + b_L) ~ 0.09 s; acceleration per volt Kt / (R (J + J_L))
    ~ 208 rad/s^2 per V; contact mode sqrt(k_s (1/J + 1/J_L)) ~ 1.7e3 rad/s (~280 Hz,
    damping ratio ~0.5), resolved by the 0.2 ms sub-step (omega h ~ 0.35). The flags are
    checked: a sub-step that would make the contact unstable is refused.

Measurement
    theta_L + Gaussian noise (std --noise, from random.Random(--seed)), quantised to the
    encoder's 2 pi / 2048 rad. The same seed and the same requests give the same answers.

Integration
    Semi-implicit (symplectic) Euler with a fixed sub-step; an `advance` that is not a
    multiple of it ends with one shorter step, so any DT (including 0) works. The input is
    held between writes. At most 60 s per `advance` (split longer waits), as for every
    driver (plants/driver_loop.py).

Protocol (one answer per request, flushed; the loop and its limits are plants/driver_loop.py)
    (start)          -> hello channels=1
    read             -> theta_L               (rad)
    write v          -> ok a                  (a = v clamped to -12 .. 12 V)
    advance DT       -> ok                    (0 <= DT <= 60 and finite, seconds)
    stop             -> ok, 0 V, exit 0
    end of stdin     -> 0 V, exit 0
    anything else    -> err MESSAGE (nothing changes)

Try it by hand
    printf 'read\\nwrite 3\\nadvance 0.5\\nread\\nwrite 0.3\\nadvance 1\\nread\\nstop\\n' | python3 dc_motor.py
    python3 dc_motor.py --backlash 0.02 --coulomb 0.02 --noise 0.001 --seed 4
"""

import argparse
import math
import os
import random
import sys

# The serve loop, shared by the drivers: plants/driver_loop.py, found from this file's place
# so that the driver runs from any working directory (bytecode is not written into the tree).
sys.dont_write_bytecode = True
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir))
from driver_loop import run  # noqa: E402

V_MIN = -12.0  # V
V_MAX = 12.0  # V


class DcMotor:
    """Motor + backlash + load, semi-implicit Euler with implicit Coulomb friction."""

    def __init__(self, a):
        self.inertia = a.inertia
        self.load_inertia = a.load_inertia
        self.torque_per_volt = a.kt / a.resistance
        self.damping = a.kt * a.ke / a.resistance + a.viscous  # back-EMF + viscous
        self.load_viscous = a.load_viscous
        self.coulomb = a.coulomb
        self.load_coulomb = a.load_coulomb
        self.delta = a.backlash
        self.stiffness = a.stiffness
        self.contact_damping = a.contact_damping
        self.substep = a.substep
        self.count = 2.0 * math.pi / a.counts  # rad per encoder count
        self.noise = a.noise
        self.rng = random.Random(a.seed)
        self.theta_m = 0.0
        self.w_m = 0.0
        self.theta_l = 0.0
        self.w_l = 0.0
        self.applied = 0.0

    def read(self):
        y = self.theta_l
        if self.noise > 0.0:
            y += self.rng.gauss(0.0, self.noise)
        return [round(y / self.count) * self.count]

    def write(self, values):
        (v,) = values
        a = V_MIN if v < V_MIN else V_MAX if v > V_MAX else v
        self.applied = a
        return [a]

    def _integrate(self, steps, h):
        """`steps` semi-implicit Euler steps of h seconds (the hot loop: locals only)."""
        thm, wm, thl, wl = self.theta_m, self.w_m, self.theta_l, self.w_l
        delta = self.delta
        ks = self.stiffness
        cs = self.contact_damping
        drive = self.torque_per_volt * self.applied
        dm = self.damping
        bl = self.load_viscous
        hj = h / self.inertia
        hjl = h / self.load_inertia
        fric = hj * self.coulomb  # the largest speed change friction can make in one step
        fric_l = hjl * self.load_coulomb
        for _ in range(steps):
            d = thm - thl
            if d > delta:
                tc = ks * (d - delta) + cs * (wm - wl)
                if tc < 0.0:
                    tc = 0.0
            elif d < -delta:
                tc = ks * (d + delta) + cs * (wm - wl)
                if tc > 0.0:
                    tc = 0.0
            else:
                tc = 0.0
            # Speed without friction, then friction as an impulse bounded by Tc h: it stops
            # the motor (and keeps it stopped) whenever it can, otherwise opposes the motion.
            w = wm + hj * (drive - dm * wm - tc)
            if w > fric:
                wm = w - fric
            elif w < -fric:
                wm = w + fric
            else:
                wm = 0.0
            w = wl + hjl * (tc - bl * wl)
            if w > fric_l:
                wl = w - fric_l
            elif w < -fric_l:
                wl = w + fric_l
            else:
                wl = 0.0
            thm += h * wm
            thl += h * wl
        self.theta_m, self.w_m, self.theta_l, self.w_l = thm, wm, thl, wl

    def advance(self, dt):
        h = self.substep
        steps = int(dt / h)
        rest = dt - steps * h
        if steps:
            self._integrate(steps, h)
        if rest > 1e-12 * h:
            self._integrate(1, rest)

    def safe_stop(self):
        self.write([0.0])


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="DC motor with Coulomb friction and backlash, a driver for the agent's line protocol."
    )
    f = p.add_argument
    f("--seed", type=int, default=0, help="seed of the measurement noise (default 0)")
    f("--backlash", type=float, default=0.01, help="delta, half the play, rad (default 0.01)")
    f("--coulomb", type=float, default=0.01, help="Tc, motor Coulomb friction, N m (default 0.01)")
    f("--load-coulomb", type=float, default=0.002, help="Tc_L, load Coulomb friction, N m (default 0.002)")
    f("--noise", type=float, default=0.0, help="extra angle noise std, rad (default 0)")
    f("--inertia", type=float, default=2e-5, help="J, motor inertia, kg m^2 (default 2e-5)")
    f("--load-inertia", type=float, default=1e-4, help="J_L, load inertia, kg m^2 (default 1e-4)")
    f("--kt", type=float, default=0.05, help="Kt, torque constant, N m/A (default 0.05)")
    f("--ke", type=float, default=0.05, help="Ke, back-EMF constant, V s/rad (default 0.05)")
    f("--resistance", type=float, default=2.0, help="R, armature resistance, ohm (default 2)")
    f("--viscous", type=float, default=1e-5, help="b, motor viscous friction, N m s/rad (default 1e-5)")
    f("--load-viscous", type=float, default=5e-5, help="b_L, load viscous friction, N m s/rad (default 5e-5)")
    f("--stiffness", type=float, default=50.0, help="k_s, gear stiffness in contact, N m/rad (default 50)")
    f("--contact-damping", type=float, default=0.03, help="c_s, contact damping, N m s/rad (default 0.03)")
    f("--counts", type=int, default=2048, help="encoder counts per revolution (default 2048)")
    f("--substep", type=float, default=2e-4, help="integration sub-step, s (default 2e-4)")
    a = p.parse_args(argv)
    for name, v in vars(a).items():
        if isinstance(v, float) and not math.isfinite(v):
            p.error(f"--{name.replace('_', '-')} must be finite")
    for name in ("inertia", "load_inertia", "kt", "resistance", "substep"):
        if getattr(a, name) <= 0.0:
            p.error(f"--{name.replace('_', '-')} must be > 0")
    for name in ("backlash", "coulomb", "load_coulomb", "noise", "ke", "viscous", "load_viscous",
                 "stiffness", "contact_damping"):
        if getattr(a, name) < 0.0:
            p.error(f"--{name.replace('_', '-')} must be >= 0")
    if a.counts < 1:
        p.error("--counts must be >= 1")
    # Stability of the explicit parts at this sub-step (symplectic Euler on the contact mode
    # x'' + 2 z x' + w^2 x = 0 is stable for (w h)^2 + 4 z h < 4; keep a factor 2 of margin;
    # the motor's own damping must not overshoot in one step either).
    h = a.substep
    inv_mass = 1.0 / a.inertia + 1.0 / a.load_inertia
    motor_damping = (a.kt * a.ke / a.resistance + a.viscous) / a.inertia
    w2 = a.stiffness * inv_mass
    z = 0.5 * (a.contact_damping * inv_mass + motor_damping)
    if w2 * h * h + 4.0 * z * h > 2.0 or motor_damping * h > 1.0:
        p.error(f"--substep {h:g} s is too long for this stiffness/damping/inertia "
                f"(contact mode {math.sqrt(w2):.0f} rad/s): use a shorter one")
    return a


def main(argv=None):
    return run(DcMotor(parse_args(argv)), 1)


if __name__ == "__main__":
    sys.exit(main())
