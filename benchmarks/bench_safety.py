"""Safety campaign (issue 7): random waveforms and wire faults against the emulated device.

Run from the repository root::

    python benchmarks/bench_safety.py --json

Plays thousands of random waveforms (good ones and ones beyond the voltage, slew or step-in limits,
or not finite) in-process and over every real wire with faults injected by the servers (dropped,
corrupted, delayed replies, disconnects, garbage), then 100 watchdog trials over real wires (see
``benchmarks/campaign.py`` for what each count means). Progress goes to stderr; the last line of
stdout is one JSON object with ``out_of_limit``, ``hangs``, ``lost``, ``watchdog_ok`` and the rest.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

if __package__:  # python -m benchmarks.<name>, or imported by the tests
    from benchmarks import campaign
else:  # python benchmarks/<name>.py: Python puts this folder on the path
    import campaign


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print only the JSON line on stdout")
    ap.add_argument("--inprocess", type=int, default=8400, help="trials without a wire")
    ap.add_argument("--per-wire", type=int, default=400, help="trials over each faulty wire")
    ap.add_argument("--watchdog", type=int, default=100, help="watchdog trials")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    t0 = time.monotonic()

    def say(msg: str) -> None:
        print(f"[{time.monotonic() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    tally = campaign.campaign(args.inprocess, args.per_wire, args.watchdog, args.seed, say)
    out = {**tally.as_dict(), "seconds": round(time.monotonic() - t0, 1),
           "wires": list(campaign.WIRES), "wire_timeout_s": campaign.WIRE_TIMEOUT_S}
    if not args.json:
        for k, v in out.items():
            print(f"{k:24s} {v}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
