"""Upload and readback throughput of the emulated stage over its real wires.

Modbus TCP on 127.0.0.1, Modbus RTU on a pty bridge and the ASCII protocol on a pty and on
``socket://127.0.0.1`` (the way a serial-to-Ethernet adapter is reached), each with a
20,000-sample waveform (upload: table length + chunks; readback: every recorder sample after the
run). Run from the repository root::

    python benchmarks/bench_transport.py --json

The last line of output is one JSON object with samples/s per transport and direction.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager

import numpy as np

from afmctl.drivers import StageBase  # noqa: E402
from afmctl.drivers.device.emulated import EmulatedDevice  # noqa: E402
from afmctl.drivers.device.modbus_server import ModbusRtuServer, ModbusTcpServer  # noqa: E402
from afmctl.drivers.device.serial_server import SerialServer  # noqa: E402
from afmctl.drivers.modbus_link import ModbusStage  # noqa: E402
from afmctl.drivers.serial_link import SerialStage  # noqa: E402
from afmctl.files.profile import ModbusRtuTransport, ModbusTcpTransport, Profile, default_profile  # noqa: E402


@contextmanager
def _stage(kind: str, profile: Profile) -> Iterator[StageBase]:
    with ExitStack() as stack:
        dev = stack.enter_context(EmulatedDevice(profile))
        if kind == "modbus_tcp":
            srv = stack.enter_context(ModbusTcpServer(dev))
            stage: StageBase = ModbusStage(profile, ModbusTcpTransport("127.0.0.1", srv.port))
        elif kind == "modbus_rtu_pty":
            rtu = stack.enter_context(ModbusRtuServer(dev))
            stage = ModbusStage(profile, ModbusRtuTransport(rtu.url))
        else:
            where = "socket://127.0.0.1:0" if kind == "serial_socket" else "pty"
            stage = SerialStage(profile, stack.enter_context(SerialServer(dev, where)).url)
        with stage:
            yield stage


def _timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def measure(kind: str, profile: Profile, n: int, repeats: int) -> dict[str, float]:
    """Best-of-``repeats`` upload and readback rates, samples/s."""
    v = 100.0 * np.sin(2 * np.pi * 5.0 * np.arange(n) / profile.sample_rate_hz)
    up, down = [], []
    with _stage(kind, profile) as stage:
        for _ in range(repeats):
            up.append(_timed(lambda: stage.upload(v)))
            stage.run(1)
            stage.wait()
            down.append(_timed(lambda: stage.read_recorder()))
            stage.safe_state()
    return {f"{kind}_upload_samples_per_s": n / min(up),
            f"{kind}_readback_samples_per_s": n / min(down)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="end with one JSON line (always printed)")
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    profile = default_profile()
    result: dict[str, float | int] = {"samples": args.samples, "repeats": args.repeats}
    names = {"modbus_tcp": "Modbus TCP loopback", "modbus_rtu_pty": "Modbus RTU on a pty",
             "serial_pty": "serial protocol on a pty",
             "serial_socket": "serial protocol on socket://"}
    for kind, label in names.items():
        r = measure(kind, profile, args.samples, args.repeats)
        result.update({k: round(x) for k, x in r.items()})
        print(f"{label:28s} upload {r[f'{kind}_upload_samples_per_s']:10.0f} samples/s   "
              f"readback {r[f'{kind}_readback_samples_per_s']:10.0f} samples/s", file=sys.stderr)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
