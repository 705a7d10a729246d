#!/usr/bin/env python3
"""A plant behind a Modbus TCP server, as a PLC would expose it: pymodbus's server (not ours)
hosting one of the example plants' physics, in real time.

The physics are the example drivers' own (plants/heater/heater.py, plants/dc-motor/
dc_motor.py); time is the wall clock: before every request is answered the plant is
advanced to now, so a read sees the plant as it is and a write acts from the moment it
arrives. The input is clamped to the actuator's range, as an actuator would.

Register map (0-based addresses, float32, high word first):
    holding 0-1   the input to apply (V)                      read-write
    input   0-1   the measured output (degC or rad)           read-only
    input   2-3   the input really applied (after the clamp)  read-only
    holding 10    a watchdog the PLC would check (not used by the physics)

Misbehaviour on demand, for the bridge's tests (seconds after the first write):
    --nan-after S       the output reads NaN
    --vanish-after S    the output's registers answer "illegal data address"
    --silent-after S    no request is answered any more (the connection stays open)

Usage
    modbus_plant.py --plant heater|dc-motor --port 5020 [--seed N] [plant flags...]
Prints `listening PORT` on stdout once it accepts connections.
"""

import argparse
import asyncio
import math
import struct
import sys

sys.dont_write_bytecode = True
from pymodbus.constants import ExcCodes  # noqa: E402
from pymodbus.server import ModbusTcpServer  # noqa: E402
from pymodbus.simulator import DataType, SimData, SimDevice  # noqa: E402

from physics import PLANTS, RealTime, load_plant  # noqa: E402

FC_READ_INPUT = 4
FC_WRITES = (6, 16)


def words(x):
    hi, lo = struct.unpack(">HH", struct.pack(">f", x))
    return [hi, lo]


def value(ws):
    return struct.unpack(">f", struct.pack(">HH", ws[0], ws[1]))[0]


class ModbusPlant(RealTime):
    """The plant behind the registers: each request catches it up first."""

    async def action(self, fc, start, address, count, registers, set_values):
        if self.misbehaving("silent_after"):
            await asyncio.sleep(3600)
        self.catch_up()
        if fc in FC_WRITES and set_values is not None and address == 0 and len(set_values) >= 2:
            v = value(set_values[:2])
            if not math.isfinite(v):
                return ExcCodes.ILLEGAL_VALUE
            self.apply(v)
        if fc == FC_READ_INPUT:
            if address < 2 and self.misbehaving("vanish_after"):
                return ExcCodes.ILLEGAL_ADDRESS
            (y,) = self.plant.read()
            if self.misbehaving("nan_after"):
                y = float("nan")
            registers[0:4] = words(y) + words(self.applied)
        return None


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--plant", choices=sorted(PLANTS), required=True)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=5020)
    p.add_argument("--nan-after", type=float)
    p.add_argument("--vanish-after", type=float)
    p.add_argument("--silent-after", type=float)
    return p.parse_known_args(argv)


async def serve(args, plant_argv):
    rt = ModbusPlant(load_plant(args.plant, plant_argv), args)
    device = SimDevice(
        id=0,
        simdata=(
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, count=16, values=0, datatype=DataType.REGISTERS)],
            [SimData(0, count=4, values=0, datatype=DataType.REGISTERS, readonly=True)],
        ),
        action=rt.action,
    )
    server = ModbusTcpServer(device, address=(args.host, args.port))
    task = asyncio.create_task(server.serve_forever())
    # serve_forever binds before it first yields; wait until the port accepts.
    for _ in range(200):
        try:
            _, w = await asyncio.open_connection(args.host, args.port)
            w.close()
            break
        except OSError:
            await asyncio.sleep(0.02)
    print(f"listening {args.port}", flush=True)
    await task


def main(argv=None):
    args, plant_argv = parse_args(argv)
    try:
        asyncio.run(serve(args, plant_argv))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
