#!/usr/bin/env python3
"""Roundness of each ring scan, live: subscribes to a machine's corrected points, and when a
scan segment ends (the next segment starts), fits a least-squares circle to its contact
points and prints the diameter and the roundness. `--plot` draws each ring's polar
deviation with matplotlib.

    python examples/roundness.py --connect tcp/127.0.0.1:7447 --machine m1 [--plot]
    python examples/roundness.py --zenoh-config deploy/zenoh-app-tls.json5 --machine m1 --json

With no points within `--timeout` seconds (60) of "ready" it says so and exits 1; an error
reaching the bus (nothing answers, a refused TLS handshake, a missing certificate) exits 1
with the package's message.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

import scancorr
from scancorr.shape import fit_circle

MIN_POINTS = 360  # a ring scan, not a dwell or a touch


def report(seg: int, pts: np.ndarray, as_json: bool, plot: bool) -> None:
    contact = pts[np.abs(pts["normal"]).sum(axis=1) > 0]
    if len(contact) < MIN_POINTS:
        return
    try:
        f = fit_circle(contact["surface"])
    except scancorr.ShapeError as e:  # a straight scan (a straightedge's) is no ring
        print(f"segment {seg}: {len(contact)} points, no circle: {e}", file=sys.stderr, flush=True)
        return
    if as_json:
        print(json.dumps({"segment": seg, "points": len(contact), "center_mm": f.center.tolist(),
                          "diameter_mm": f.diameter, "roundness_um": f.peak_to_valley * 1e3,
                          "rms_um": f.rms * 1e3}), flush=True)
    else:
        print(f"segment {seg}: {len(contact)} points, Ø {f.diameter:.5f} mm, roundness {f.peak_to_valley * 1e3:.2f} µm",
              flush=True)
    if plot:
        import matplotlib.pyplot as plt

        rel = contact["surface"] - f.center
        th = np.arctan2(rel[:, 1], rel[:, 0])
        dev = f.residuals * 1e3
        scale = max(np.abs(dev).max(), 1e-3)
        ax = plt.figure(figsize=(5, 5)).add_subplot(projection="polar")
        ax.plot(th, 2 * scale + dev, lw=0.8)
        ax.plot(np.linspace(0, 2 * np.pi, 361), np.full(361, 2 * scale), "k--", lw=0.6)
        ax.set_yticklabels([])
        ax.set_title(f"segment {seg}: Ø {f.diameter:.4f} mm, roundness {f.peak_to_valley * 1e3:.2f} µm\n(deviation ×, circle = least-squares)")
        plt.show()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--connect", help="zenoh endpoint, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--zenoh-config", help="zenoh configuration file (TLS deployments)")
    ap.add_argument("--machine", default="m1")
    ap.add_argument("--prefix", default="cmm")
    ap.add_argument("--idle", type=float, default=None, help="stop after this many seconds without points")
    ap.add_argument("--timeout", type=float, default=60.0,
                    help="fail when no points arrive within this many seconds of ready (default 60)")
    ap.add_argument("--json", action="store_true", help="one JSON line per ring")
    ap.add_argument("--plot", action="store_true", help="draw each ring's polar deviation (matplotlib)")
    a = ap.parse_args()
    if a.connect is None and a.zenoh_config is None:
        ap.error("give --connect or --zenoh-config")
    if not a.timeout > 0:
        ap.error("--timeout must be a positive number of seconds")
    try:
        return follow(a)
    except scancorr.ScancorrError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


def follow(a: argparse.Namespace) -> int:
    with scancorr.connect(a.connect, zenoh_config=a.zenoh_config, prefix=a.prefix, timeout=min(a.timeout, 3.0)) as bus:
        with bus.subscribe_points(a.machine) as sub:
            print("ready", file=sys.stderr, flush=True)
            seg, parts = None, []
            for batch in sub.batches(idle=a.idle, first_timeout=a.timeout):
                p = batch.points
                # Split the batch where the segment changes.
                cuts = np.flatnonzero(np.diff(p["segment_id"].astype(np.int64))) + 1
                for chunk in np.split(p, cuts):
                    s = int(chunk["segment_id"][0])
                    if seg is not None and s != seg:
                        report(seg, np.concatenate(parts), a.json, a.plot)
                        parts = []
                    seg = s
                    parts.append(chunk)
            if seg is None:
                print(
                    f"error: no points on {sub.key} within {a.timeout:g} s (is machine `{a.machine}` streaming, "
                    "and scancorrd serving it? `scancorr status` lists the machines served)",
                    file=sys.stderr,
                )
                return 1
            if parts:
                report(seg, np.concatenate(parts), a.json, a.plot)
            if sub.missed:
                print(f"warning: {sub.missed} point(s) missed (gaps in seq)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
