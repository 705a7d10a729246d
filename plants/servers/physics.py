"""The example plants' physics for the servers here: the drivers' own classes
(plants/heater/heater.py, plants/dc-motor/dc_motor.py), built from their own flags."""

import importlib.util
import os

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
