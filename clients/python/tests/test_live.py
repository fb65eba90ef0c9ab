"""Against a live scancorrd fed by `scancorr replay`: the subscriber receives every point
with no missed seq and the same values as `scancorr correct` offline; calibrations round-trip;
the example app measures the ring."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys
import threading
import time
from typing import Dict, List

import numpy as np
import pytest

import scancorr

from conftest import ROOT, Service, binary, run


def replay(d: pathlib.Path, bag: str, endpoint: str) -> None:
    run(d, "replay", "--bag", bag, "--speed", "max", "--connect", endpoint)


def test_subscriber_receives_every_point_as_offline(ring: Dict, service: Service) -> None:
    d = ring["dir"]
    off = ring["offline"]
    with scancorr.connect(service.endpoint) as bus:
        put = bus.put_calibration("m1", d / "drift.json")
        assert put["version"] == 1
        alarms: List[np.ndarray] = []
        with bus.subscribe_points("m1") as sub, bus.subscribe_alarms("m1", callback=alarms.append) as asub:
            time.sleep(1.0)  # the subscriptions' routes to scancorrd
            replay(d, "drift.mcap", service.endpoint)
            got = [b.points for b in sub.batches(idle=3.0, first_timeout=30.0)]
            missed = sub.missed
        assert not asub.errors
    live = np.concatenate(got)
    assert len(live) == off["points"], f"{len(live)} points live, {off['points']} offline"
    assert missed == 0
    assert np.array_equal(live["seq"], np.arange(len(live)))
    # The same values, to the bit, as the offline corrector's bag.
    ref = scancorr.read_bag(d / "drift-off.mcap").points()
    for f in ("t_ns", "sample_seq", "surface", "tip_center", "normal", "calibration_version", "valid", "segment_id", "tip_id"):
        assert np.array_equal(live[f], ref[f]), f
    assert (~live["valid"]).sum() == off["points_flagged"] > 0
    # Every alarm message (raised and cleared) as the offline bag holds them; the summary
    # counts the raised ones.
    a = np.concatenate(alarms)
    assert np.array_equal(a, scancorr.read_bag(d / "drift-off.mcap").alarms())
    assert a["raised"].sum() == off["alarms"] == 2 and (~a["raised"]).sum() == 2


def test_breakdown_on_request_sums_to_the_correction(ring: Dict, service: Service) -> None:
    d = ring["dir"]
    with scancorr.connect(service.endpoint) as bus:
        bus.put_calibration("m1", d / "drift.json")
        batches: List[scancorr.PointBatch] = []
        with bus.subscribe_points("m1", breakdown=True, callback=batches.append) as sub:
            time.sleep(1.0)
            replay(d, "drift.mcap", service.endpoint)
            t0 = time.monotonic()
            while sum(len(b.points) for b in batches) < ring["offline"]["points"] and time.monotonic() - t0 < 30:
                time.sleep(0.1)
        assert not sub.errors and sub.missed == 0
    assert sum(len(b.points) for b in batches) == ring["offline"]["points"]
    effects = set().union(*(b.breakdown.keys() for b in batches))
    assert set(ring["offline"]["effect_points"]) == effects
    # Each effect's correction is there for as many points as the offline summary says.
    for e, n in ring["offline"]["effect_points"].items():
        seen = sum(int((np.abs(b.breakdown[e]).sum(axis=1) > 0).sum()) for b in batches if e in b.breakdown)
        assert seen <= n and seen > 0.9 * n, (e, seen, n)


def test_calibrations_round_trip(ring: Dict, service: Service) -> None:
    d = ring["dir"]
    doc = json.loads((d / "v1.json").read_text())
    with scancorr.connect(service.endpoint) as bus:
        with pytest.raises(scancorr.NotServed):
            bus.status("m1")
        assert bus.put_calibration("m1", doc) == {"machine": "m1", "version": 1, "parent_version": None}
        v2 = bus.put_calibration("m1", doc, note="from python")
        assert v2["version"] == 2 and v2["parent_version"] == 1
        cur = bus.get_calibration("m1")
        assert cur["version"] == 2 and cur["note"] == "from python"
        assert cur["effects"] == bus.get_calibration("m1", version=1)["effects"] == doc["effects"]
        h = bus.history("m1")
        assert [x["version"] for x in h] == [1, 2]
        # The audit trail names who asked (as claimed) and the action.
        assert [x["audit"]["action"] for x in h] == ["put", "put"]
        assert all("(claimed)" in x["audit"]["by"] for x in h)
        # A rollback makes version 1 current again as version 3.
        r = bus.rollback("m1", 1)
        assert r["version"] == 3 and r["parent_version"] == 2
        assert bus.get_calibration("m1")["note"].startswith("rollback to v1")
        assert bus.history("m1")[-1]["audit"]["action"] == "rollback to v1"
        with pytest.raises(scancorr.ServiceError, match="already current"):
            bus.rollback("m1", 3)
        bus.put_calibration("m1", doc, note="from python")
        st = bus.status("m1")
        assert st["calibration_version"] == 4
        assert "m1" in bus.machines()
        # The service's refusals, as exceptions with its message.
        with pytest.raises(scancorr.ServiceError, match="no calibration version 9"):
            bus.get_calibration("m1", version=9)
        bad = dict(doc, machine_id="m2")
        with pytest.raises(scancorr.ServiceError, match="m2"):
            bus.put_calibration("m1", bad)
        assert bus.get_calibration("m1")["version"] == 4  # nothing changed
        with pytest.raises(scancorr.ServiceError, match="no calibration"):
            bus.get_calibration("m7")
        # A name from outside never reaches a key expression unchecked.
        for name in ("m1/**", "", "a b", "x" * 65):
            with pytest.raises(ValueError, match="machine id"):
                bus.get_calibration(name)
    with pytest.raises(ValueError, match="endpoint"):
        scancorr.connect()


def test_a_service_of_another_prefix_is_no_service(service: Service) -> None:
    """Connected (something answers), but no scancorrd serves the prefix: `NoService` within
    the query timeout, in the CLI's words (tests/test_errors.py: nothing listening at all)."""
    with scancorr.connect(service.endpoint, prefix="other", query_timeout=1.0) as bus:
        t0 = time.monotonic()
        with pytest.raises(scancorr.NoService, match=r"^no scancorrd answered on `other/m1/calibration\?history` \(is it running"):
            bus.history("m1")
        assert time.monotonic() - t0 < 5


def test_the_example_reports_the_ring_diameter_within_1um(ring: Dict, service: Service) -> None:
    d = ring["dir"]
    truth = 2.0 * ring["truth"]["features"][0]["radius_mm"]
    with scancorr.connect(service.endpoint) as bus:
        bus.put_calibration("m1", d / "v1.json")  # the true calibration (sim --calib-out)
    ex = subprocess.Popen(
        [sys.executable, str(ROOT / "clients/python/examples/roundness.py"), "--connect", service.endpoint,
         "--machine", "m1", "--idle", "3", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    assert ex.stderr is not None
    ready = ex.stderr.readline()
    assert ready.strip() == "ready", ready + ex.stderr.read()
    time.sleep(1.0)
    replay(d, "r.mcap", service.endpoint)
    out, err = ex.communicate(timeout=60)
    assert ex.returncode == 0, err
    rings = [json.loads(line) for line in out.splitlines() if line.strip()]
    assert len(rings) == 2, out  # CCW and CW
    for r in rings:
        assert abs(r["diameter_mm"] - truth) < 1e-3, (r, truth)
        assert 0 < r["roundness_um"] < 5, r


def test_a_zenoh_configuration_file_reaches_the_service(ring: Dict, service: Service, tmp_path: pathlib.Path) -> None:
    """`connect(zenoh_config=FILE)`, as a TLS deployment is reached (deploy/: certificates in
    the file); here a plain TCP endpoint in the file."""
    cfg = tmp_path / "app.json5"
    cfg.write_text(
        "{ mode: 'client', connect: { endpoints: ['%s'] }, scouting: { multicast: { enabled: false } } }"
        % service.endpoint
    )
    with scancorr.connect(zenoh_config=cfg) as bus:
        assert bus.put_calibration("m1", ring["dir"] / "v1.json")["version"] == 1
        assert [h["version"] for h in bus.history("m1")] == [1]
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'nonsense' ")
    with pytest.raises(ValueError, match="bad.json5"):
        scancorr.connect(zenoh_config=bad)


def test_the_readme_live_example_runs(ring: Dict, service: Service) -> None:
    """The package README's live example as printed (its endpoint this test's scancorrd's; its
    `import scancorr` the ten lines' above it) prints every point of a replayed ring, none
    missed."""
    import re

    text = (ROOT / "clients" / "python" / "README.md").read_text()
    code = re.findall(r"```python\n(.*?)```", text, re.S)[1]
    assert 'scancorr.connect("tcp/127.0.0.1:7447")' in code, code
    d = ring["dir"]
    (d / "live_example.py").write_text("import scancorr\n" + code.replace("tcp/127.0.0.1:7447", service.endpoint))
    with scancorr.connect(service.endpoint) as bus:
        bus.put_calibration("m1", d / "drift.json")
    ex = subprocess.Popen([sys.executable, "live_example.py"], cwd=d, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(2.0)  # connected, subscribed and routed
        replay(d, "drift.mcap", service.endpoint)
        out, err = ex.communicate(timeout=60)
    finally:
        ex.kill()
    assert ex.returncode == 0, err
    lines = out.splitlines()
    assert lines and all(l.endswith("missed so far: 0") for l in lines), out
    assert sum(int(l.split()[0]) for l in lines) == ring["offline"]["points"], out

