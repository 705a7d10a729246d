"""The example plants' physics for the servers here: the drivers' own classes
(plants/heater/heater.py, plants/dc-motor/dc_motor.py), built from their own flags."""

import importlib.util
import os
import time

HERE = os.path.dirname(os.path.abspath(__file__))
PLANTS = {
    "heater": (os.path.join(HERE, os.pardir, "heater", "heater.py"), "Heater"),
    "dc-motor": (os.path.join(HERE, os.pardir, "dc-motor", "dc_motor.py"), "DcMotor"),
}


def load_plant(name, argv):
    """The example driver's plant, built from its own command-line flags."""
    path, cls = PLANTS[name]
    spec = importlib.util.spec_from_file_location(name.replace("-", "_"), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    args = module.parse_args(argv)
    if cls == "Heater":
        return module.Heater(args.ambient, args.gain, args.tau, args.dead_time, args.noise, args.seed)
    return module.DcMotor(args)


class RealTime:
    """A plant advanced to the wall clock: `catch_up` before it is read or written. It
    misbehaves on demand (`args.nan_after`, `vanish_after`, `silent_after`: seconds after
    the first write)."""

    def __init__(self, plant, args):
        self.plant, self.args = plant, args
        self.t0 = time.monotonic()
        self.t = 0.0
        self.first_write = None
        self.applied = 0.0

    def catch_up(self):
        now = time.monotonic() - self.t0
        if now > self.t:
            self.plant.advance(now - self.t)
            self.t = now

    def misbehaving(self, flag):
        after = getattr(self.args, flag)
        return after is not None and self.first_write is not None and self.t - self.first_write >= after

    def apply(self, v):
        """Write `v` now (the plant clamps it); what it applies is kept in `applied`."""
        self.catch_up()
        if self.first_write is None:
            self.first_write = self.t
        (self.applied,) = self.plant.write([v])
