#!/usr/bin/env python3
"""Benchmark: decoding corrected points into numpy.

Makes a campaign bag (331 k points: `scancorr sim --program campaign` then `scancorr
correct`) unless given one, takes its CorrectedPointBatch payloads into memory, and times
`scancorr.arrays.decode_points` over all of them, several rounds; prints the time per round
(min / median / max) and points per second. The payloads are read once, before timing (the
bag reader's own speed is not what this measures).

    python clients/python/bench/decode_points.py [--bag corrected.mcap] [--rounds 5]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

import scancorr
from scancorr.arrays import decode_points


def payloads(bag: str) -> list:
    from scancorr import _mcap

    out = []

    def keep(_id, _channel, schema, _t, data) -> None:
        if schema is not None and schema.name == "scancorr.v1.CorrectedPointBatch":
            out.append(bytes(data))

    _mcap.read(bag, keep)  # verified, as read_bag reads it
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", help="a corrected bag (default: make a campaign's)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--scancorr", default=os.environ.get("SCANCORR", "scancorr"),
                    help="the scancorr binary (to make the bag)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bag = a.bag
        if bag is None:
            t = pathlib.Path(tmp)
            run = lambda *args: subprocess.run([a.scancorr, *args], cwd=t, check=True, capture_output=True)
            run("sim", "--program", "campaign", "--out", "c.mcap", "--calib-out", "v1.json")
            run("correct", "--bag", "c.mcap", "--calib", "v1.json", "--out", "cc.mcap")
            bag = str(t / "cc.mcap")
        data = payloads(bag)
    n = 0
    times = []
    for _ in range(max(1, a.rounds)):
        t0 = time.perf_counter()
        arrs = [decode_points(d) for d in data]
        pts = np.concatenate(arrs)
        times.append(time.perf_counter() - t0)
        n = len(pts)
    med = statistics.median(times)
    # Against decoding into dicts (what the package's predecessor handed out), on every tenth
    # batch, in the same run.
    from google.protobuf.json_format import MessageToDict

    from scancorr.v1 import scancorr_pb2 as pb

    sub = data[::10]
    t0 = time.perf_counter()
    for d in sub:
        MessageToDict(pb.CorrectedPointBatch.FromString(d), preserving_proto_field_name=True)
    t_dict = time.perf_counter() - t0
    t0 = time.perf_counter()
    for d in sub:
        decode_points(d)
    t_np = time.perf_counter() - t0
    print(f"decode_points: {n} points in {len(data)} batches; per round min {min(times):.3f} s, "
          f"median {med:.3f} s, max {max(times):.3f} s over {len(times)} rounds; "
          f"{n / med / 1e6:.2f} M points/s ({med / max(n, 1) * 1e9:.0f} ns/point)")
    print(f"dicts (MessageToDict) on every tenth batch: {t_dict:.3f} s against {t_np:.3f} s into numpy: "
          f"{t_dict / t_np:.1f}x slower")
    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, scancorr {scancorr.__version__}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
