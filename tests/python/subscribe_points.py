#!/usr/bin/env python3
"""Independent live consumer of scancorrd: the `eclipse-zenoh` Python client plus
`google.protobuf`, with message classes built at run time from the descriptor set a bag
carries (through the small `scancorr_client` package in clients/python; no Rust code).

    python subscribe_points.py --connect tcp/127.0.0.1:7447 --machine m1 \\
        --descriptor-bag r.mcap [--idle 3] [--max-seconds 90] [--mode peer] [--prefix cmm]

Subscribes to `<prefix>/<machine>/corrected/points` (scancorr.v1.CorrectedPointBatch) and
`<prefix>/<machine>/alarms/estimator` (scancorr.v1.EstimatorAlarm), prints `ready` on stderr
once both are declared, and decodes every message. It stops when nothing arrived for
`--idle` seconds after the first message (or after `--max-seconds` in all), then prints one
JSON document on stdout:

    {"points": N, "batches": N, "first_seq": S, "last_seq": S, "gaps": K, "missing": M,
     "alarms": A, "calibration_versions": [1, ...], "sample_surface": [x, y, z],
     "surface_sum": [sx, sy, sz], "machine_mismatches": 0, "decode_errors": 0,
     "seconds": T}

`gaps` counts the places where a point's `seq` is not the previous one + 1 (`missing`: the
numbers skipped); `sample_surface` is the first point's surface, `surface_sum` the sums of the
surface coordinates over all points. Exit code: 0; 1 if a message did not decode, a point
names another machine, or no message arrived at all; 2 on bad arguments or a descriptor set
that cannot be loaded.
"""

import argparse
import json
import os
import sys
import time

try:
    import zenoh  # noqa: F401 - checked here for a clear message
    from google.protobuf import descriptor_pb2  # noqa: F401
except ImportError as e:  # pragma: no cover - environment problem
    sys.exit(
        f"subscribe_points.py: {e}: run with the interpreter printed by scripts/python-env.sh "
        "(it installs tests/python/requirements.txt)"
    )

try:
    import scancorr_client
except ImportError:  # not on PYTHONPATH: use the copy in this repository
    sys.path.insert(
        0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "clients", "python")
    )
    import scancorr_client

from scancorr_client.points import DecodeError


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--connect", action="append", required=True, help="zenoh endpoint (repeatable)")
    p.add_argument("--machine", required=True)
    p.add_argument("--prefix", default="cmm")
    p.add_argument("--mode", default="peer", choices=["peer", "client"])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--descriptor-bag", help="a scancorr bag whose schema is the descriptor set")
    g.add_argument("--descriptor", help="a serialized FileDescriptorSet (.bin)")
    p.add_argument("--idle", type=float, default=3.0, help="stop after this many quiet seconds")
    p.add_argument("--max-seconds", type=float, default=90.0, help="stop after this long in all")
    return p.parse_args(argv)


class Stats:
    def __init__(self, machine):
        self.machine = machine
        self.points = 0
        self.batches = 0
        self.first_seq = None
        self.last_seq = None
        self.gaps = 0
        self.missing = 0
        self.alarms = 0
        self.versions = set()
        self.sample_surface = None
        self.sum = [0.0, 0.0, 0.0]
        self.machine_mismatches = 0
        self.decode_errors = 0

    def on_points(self, batch):
        self.batches += 1
        for p in batch["points"]:
            seq = p["seq"]
            if self.last_seq is None:
                self.first_seq = seq
            elif seq != self.last_seq + 1:
                self.gaps += 1
                if seq > self.last_seq + 1:
                    self.missing += seq - self.last_seq - 1
                print(f"subscribe_points.py: seq jumps from {self.last_seq} to {seq}", file=sys.stderr)
            self.last_seq = seq
            self.points += 1
            if p["machine_id"] != self.machine:
                self.machine_mismatches += 1
            self.versions.add(p["calibration_version"])
            s = p["surface"] or {"x": 0.0, "y": 0.0, "z": 0.0}
            xyz = [s["x"], s["y"], s["z"]]
            if self.sample_surface is None:
                self.sample_surface = xyz
            for i in range(3):
                self.sum[i] += xyz[i]

    def report(self, seconds):
        return {
            "points": self.points,
            "batches": self.batches,
            "first_seq": self.first_seq,
            "last_seq": self.last_seq,
            "gaps": self.gaps,
            "missing": self.missing,
            "alarms": self.alarms,
            "calibration_versions": sorted(self.versions),
            "sample_surface": self.sample_surface,
            "surface_sum": self.sum,
            "machine_mismatches": self.machine_mismatches,
            "decode_errors": self.decode_errors,
            "seconds": round(seconds, 3),
        }


def main(argv):
    a = parse_args(argv)
    t0 = time.monotonic()
    deadline = t0 + a.max_seconds
    try:
        fds = scancorr_client.load_descriptor_set(a.descriptor_bag or a.descriptor)
        classes = scancorr_client.message_classes(fds)
    except (OSError, ValueError) as e:
        print(f"subscribe_points.py: descriptor set: {e}", file=sys.stderr)
        return 2

    st = Stats(a.machine)
    session = scancorr_client.open_session(a.connect, mode=a.mode)
    try:
        with scancorr_client.subscribe_points(session, a.machine, prefix=a.prefix, classes=classes) as sub:
            print("ready", file=sys.stderr, flush=True)
            got_one = False
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    print("subscribe_points.py: --max-seconds reached", file=sys.stderr)
                    break
                try:
                    msg = sub.recv(timeout=min(a.idle, left) if got_one else left)
                except DecodeError as e:
                    st.decode_errors += 1
                    print(f"subscribe_points.py: {e}", file=sys.stderr)
                    got_one = True
                    continue
                if msg is None:
                    if got_one:
                        break
                    continue  # the deadline check above ends the wait
                got_one = True
                if msg.kind == "points":
                    st.on_points(msg.value)
                else:
                    st.alarms += 1
    finally:
        session.close()

    json.dump(st.report(time.monotonic() - t0), sys.stdout, sort_keys=True)
    sys.stdout.write("\n")
    sys.stdout.flush()
    if st.decode_errors or st.machine_mismatches:
        print(
            f"subscribe_points.py: {st.decode_errors} message(s) did not decode, "
            f"{st.machine_mismatches} point(s) name another machine",
            file=sys.stderr,
        )
        return 1
    if st.batches == 0 and st.alarms == 0:
        print("subscribe_points.py: no message arrived", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
