"""Python = CLI (issue 47, item 3): each error the `scancorr` CLI reports and its twin in the
package say the same thing, and the package never returns normally from what the CLI refuses:
nothing listening, an endpoint without its protocol, a TLS file missing, a TLS handshake or a
query refused by a router, a straightedge fitted as a circle, an example with nothing to read.
(Every metadata record of a bag kept: tests/test_bag.py.)"""

from __future__ import annotations

import json
import pathlib
import re
import signal
import socket
import subprocess
import sys
import time
from typing import Iterator, List

import numpy as np
import pytest

import scancorr
from scancorr import shape

from conftest import ROOT, Service, binary, free_port, run

HINT = "(is scancorrd or a zenoh router running and listening on it?)"


def cli_error(cwd: pathlib.Path, *args: str) -> str:
    """`scancorr ARGS` must fail; its error line, without `error: ` and zenoh's own words."""
    r = subprocess.run([str(binary("scancorr")), *args], cwd=cwd, capture_output=True, text=True, timeout=30)
    assert r.returncode != 0, f"scancorr {' '.join(args)} succeeded:\n{r.stdout}"
    line = [l for l in r.stderr.splitlines() if l.startswith("error: ")]
    assert line, r.stderr
    return without_zenoh(line[0][len("error: "):])


def without_zenoh(text: str) -> str:
    return re.sub(r" \[zenoh: .*\]$", "", str(text))


def test_connecting_to_nothing_fails_as_the_cli_does(tmp_path: pathlib.Path) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    cli = cli_error(tmp_path, "status", "--connect", ep)
    t0 = time.monotonic()
    with pytest.raises(scancorr.NotConnected) as e:
        scancorr.connect(ep, timeout=0.5)
    assert time.monotonic() - t0 < 3
    assert without_zenoh(e.value) == cli == f"cannot connect to {ep}: nothing answers there {HINT}"
    assert e.value.endpoints == [ep]
    assert isinstance(e.value, ConnectionError) and isinstance(e.value, scancorr.ScancorrError)
    # The same through a configuration file naming the endpoint.
    cfg = tmp_path / "app.json5"
    cfg.write_text("{ mode: 'client', connect: { endpoints: ['%s'] } }" % ep)
    with pytest.raises(scancorr.NotConnected, match=re.escape(f"cannot connect to {ep}: nothing answers there")):
        scancorr.connect(zenoh_config=cfg, timeout=0.5)


@pytest.mark.parametrize("endpoint", ["127.0.0.1:{p}", "localhost", "foo/127.0.0.1:{p}", "tcp/", "udp/?x=1"])
def test_a_bad_endpoint_is_named_as_the_cli_names_it(tmp_path: pathlib.Path, endpoint: str) -> None:
    endpoint = endpoint.format(p=free_port())
    cli = cli_error(tmp_path, "status", "--connect", endpoint)
    with pytest.raises(scancorr.BadEndpoint) as e:
        scancorr.connect(endpoint)
    assert cli.startswith("--connect ") and str(e.value).startswith("endpoint ")
    assert str(e.value)[len("endpoint "):] == cli[len("--connect "):]
    assert json.dumps(endpoint) in str(e.value) and "/HOST:PORT, e.g. tcp/127.0.0.1:" in str(e.value)
    assert e.value.endpoint == endpoint and isinstance(e.value, ValueError)


def test_a_missing_or_unreadable_tls_file_is_named(tmp_path: pathlib.Path) -> None:
    certs = tmp_path / "tls"
    certs.mkdir()
    for missing, key in [(certs / "ca.pem", "root_ca_certificate"), (certs / "app-key.pem", "connect_private_key")]:
        have = {"ca.pem", "app-key.pem", "app-cert.pem"} - {missing.name}
        for n in have:
            (certs / n).write_text("-----BEGIN CERTIFICATE-----\n")
        cfg = tmp_path / "app.json5"
        cfg.write_text(
            "{ mode: 'client', connect: { endpoints: ['tls/127.0.0.1:%d'] }, transport: { link: { tls: {"
            " root_ca_certificate: '%s', connect_private_key: '%s', connect_certificate: '%s', enable_mtls: true } } } }"
            % (free_port(), certs / "ca.pem", certs / "app-key.pem", certs / "app-cert.pem")
        )
        with pytest.raises(scancorr.TlsError) as e:
            scancorr.connect(zenoh_config=cfg, timeout=0.5)
        assert e.value.key == f"transport/link/tls/{key}" and e.value.path == str(missing)
        said = (
            f"`transport/link/tls/{key}`: cannot read the TLS certificate or key "
            f"file {missing}: No such file or directory"
        )
        assert str(e.value) == f"zenoh configuration {cfg}: {said}"
        # The CLI's twin: the same words, the file named by the flag that gave it.
        assert cli_error(tmp_path, "status", "--zenoh-config", str(cfg)) == f"--zenoh-config {cfg}: {said}"
        for n in have:
            (certs / n).unlink()
    # A folder where a file should be: unreadable, named.
    (certs / "ca.pem").mkdir()
    with pytest.raises(scancorr.TlsError, match=re.escape(f"file {certs / 'ca.pem'}: Is a directory")):
        scancorr.connect(zenoh_config=cfg, timeout=0.5)


def start(cmd: List[str], cwd: pathlib.Path, log: str, port: int) -> subprocess.Popen:
    p = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=open(cwd / log, "wb"))
    t0 = time.monotonic()
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return p
        except OSError:
            if p.poll() is not None or time.monotonic() - t0 > 20:
                p.kill()
                pytest.fail(f"{cmd[0]} did not start:\n{(cwd / log).read_text()}")
            time.sleep(0.05)


def stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def test_a_tls_handshake_the_router_refuses_is_refused(tmp_path: pathlib.Path) -> None:
    """A router with mutual TLS (as deploy/router.json5): a certificate of another CA is
    `Refused` (something listens there), the CA's own connects."""
    c = tmp_path / "certs"
    subprocess.run(["bash", str(ROOT / "scripts/make-certs.sh"), str(c)], check=True, capture_output=True)
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    (tmp_path / "router.json5").write_text(
        "{ mode: 'router', listen: { endpoints: ['%s'] }, scouting: { multicast: { enabled: false } },"
        " transport: { link: { tls: { root_ca_certificate: '%s', listen_private_key: '%s',"
        " listen_certificate: '%s', enable_mtls: true } } } }"
        % (ep, c / "ca.pem", c / "router-key.pem", c / "router-cert.pem")
    )

    def client(who: str) -> pathlib.Path:
        f = tmp_path / f"{who}.json5"
        f.write_text(
            "{ mode: 'client', connect: { endpoints: ['%s'] }, transport: { link: { tls: {"
            " root_ca_certificate: '%s', connect_private_key: '%s', connect_certificate: '%s', enable_mtls: true } } } }"
            % (ep, c / "ca.pem", c / f"{who}-key.pem", c / f"{who}-cert.pem")
        )
        return f

    router = start([str(binary("scancorr-router")), "-c", "router.json5"], tmp_path, "router.log", port)
    try:
        with scancorr.connect(zenoh_config=client("app-shape-analysis"), timeout=3) as bus:
            assert bus.machines(timeout=0.5) == []
        with pytest.raises(scancorr.Refused) as e:
            scancorr.connect(zenoh_config=client("rogue"), timeout=1)
        assert str(e.value).startswith(f"cannot connect to {ep}: something listens at {ep} but no zenoh session")
        assert "TLS handshake" in str(e.value)
        # The CLI's twin, with the same file: the same words.
        assert without_zenoh(e.value) == cli_error(tmp_path, "status", "--zenoh-config", str(client("rogue")))
    finally:
        stop(router)


@pytest.fixture
def acl_router(tmp_path: pathlib.Path) -> Iterator[str]:
    """A router whose access control denies every query on `cmm/*/calibration` (reading
    calibrations) and allows the rest, and a scancorrd behind it; yields the endpoint."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    (tmp_path / "router.json5").write_text(
        "{ mode: 'router', listen: { endpoints: ['%s'] }, scouting: { multicast: { enabled: false } },"
        " access_control: { enabled: true, default_permission: 'allow',"
        " rules: [ { id: 'no-read', messages: ['query'], flows: ['ingress'], permission: 'deny',"
        " key_exprs: ['cmm/*/calibration'] } ], subjects: [ { id: 'local', interfaces: ['lo'] } ],"
        " policies: [ { rules: ['no-read'], subjects: ['local'] } ] } }" % ep
    )
    (tmp_path / "svc.json5").write_text(
        "{ mode: 'client', listen: [], connect: ['%s'], prefix: 'cmm', data_dir: '%s' }" % (ep, tmp_path / "data")
    )
    router = start([str(binary("scancorr-router")), "-c", "router.json5"], tmp_path, "router.log", port)
    svc = subprocess.Popen([str(binary("scancorrd")), "--config", "svc.json5"], cwd=tmp_path,
                           stdout=subprocess.DEVNULL, stderr=open(tmp_path / "svc.log", "wb"))
    try:
        yield ep
    finally:
        stop(svc)
        stop(router)


def test_a_query_the_router_denies_is_refused_not_missing(tmp_path: pathlib.Path, acl_router: str) -> None:
    ep = acl_router
    run(tmp_path, "sim", "--program", "ring", "--out", "r.mcap", "--calib-out", "v1.json")
    # An unserved machine: no scancorrd answers — the CLI's words, the CLI alongside.
    cli = subprocess.Popen([str(binary("scancorr")), "calib", "history", "--machine", "m9", "--connect", ep],
                           cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with scancorr.connect(ep) as bus:
        # Writing is allowed (retried until scancorrd's route through the router is there).
        assert bus.put_calibration("m1", tmp_path / "v1.json")["version"] == 1
        bus.query_timeout = 1.0
        t0 = time.monotonic()
        with pytest.raises(scancorr.Refused) as e:
            bus.history("m1")
        assert time.monotonic() - t0 < 6
        assert str(e.value).startswith(
            "no answer on `cmm/m1/calibration?history` although scancorrd serves machine `m1` "
            "(its liveliness token `cmm/m1/scancorrd` is seen): the query was refused on its way"
        ), e.value
        assert "access control" in str(e.value)
        # The CLI's twin names the refusal as a refusal, in the same words.
        assert cli_error(tmp_path, "calib", "history", "--machine", "m1", "--connect", ep) == str(e.value)
        with pytest.raises(scancorr.Refused) as g:
            bus.get_calibration("m1")
        assert cli_error(tmp_path, "calib", "get", "--machine", "m1", "--connect", ep) == str(g.value)
        assert bus.status("m1")["calibration_version"] == 1  # status queries are allowed
        with pytest.raises(scancorr.NoService) as n:
            bus.history("m9")
    _, err = cli.communicate(timeout=30)
    assert cli.returncode != 0
    cli_line = [l for l in err.splitlines() if l.startswith("error: ")][0][len("error: "):]
    assert str(n.value) == cli_line == (
        "no scancorrd answered on `cmm/m9/calibration?history` (is it running, reachable and serving this prefix?)"
    )


@pytest.fixture(scope="module")
def straightedge(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    d = tmp_path_factory.mktemp("straightedge")
    run(d, "sim", "--program", "straightedge", "--out", "s.mcap", "--calib-out", "v1.json")
    run(d, "correct", "--bag", "s.mcap", "--calib", "v1.json", "--out", "c.mcap")
    return d


def test_the_readme_example_refuses_a_straightedge_as_a_circle(straightedge: pathlib.Path) -> None:
    """The README's ten lines on a straightedge's scans: a `ShapeError` in the words of the
    core's guard, no circle of kilometres."""
    text = (ROOT / "clients" / "python" / "README.md").read_text()
    code = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    (straightedge / "example.py").write_text(code)
    r = subprocess.run([sys.executable, "example.py", "c.mcap"], cwd=straightedge, capture_output=True, text=True)
    assert r.returncode != 0 and "Ø" not in r.stdout, r.stdout
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("scancorr.errors.ShapeError: circle fit: the points span "), r.stderr
    assert last.endswith(
        "the points lie on a nearly straight line, the circle is undetermined; scan more of the circle's circumference"
    ), last


def test_shape_guards_are_the_cores(straightedge: pathlib.Path) -> None:
    pts = scancorr.read_bag(straightedge / "c.mcap").points()
    contact = pts[pts["valid"] & (abs(pts["normal"]).sum(axis=1) > 0)]
    ids, counts = np.unique(contact["segment_id"], return_counts=True)
    seg = contact[contact["segment_id"] == ids[np.argmax(counts)]]["surface"]  # a scan along the edge
    assert len(seg) > 10000
    with pytest.raises(scancorr.ShapeError, match=r"span 0\.00\d+° of the best-fit circle"):
        shape.fit_circle(seg)
    with pytest.raises(scancorr.ShapeError, match=r"span 0\.00\d+°"):
        shape.roundness(seg)
    # The same points as a line: straight to some µm.
    assert shape.straightness(seg) < 0.05
    # Without the arc guard, the circle the CLI fits (the same guards then).
    assert shape.fit_circle(seg, min_arc_deg=0).diameter > 1e6
    # The core's words for the core's cases (service/core/src/shape/mod.rs ShapeError).
    line = [[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3.0]]
    with pytest.raises(scancorr.ShapeError, match=r"^circle fit: the points are collinear: scan more of the circle's circumference \(at least 3 points not on one line\)$"):
        shape.fit_circle(line)
    with pytest.raises(scancorr.ShapeError, match=r"^plane fit: the points are collinear: the plane is undetermined"):
        shape.fit_plane(line)
    with pytest.raises(scancorr.ShapeError, match=r"^sphere fit: a sphere fit needs at least 4 points, got 3: measure at least 1 more point\(s\) on the feature$"):
        shape.fit_sphere(line[:3])
    # A line a hair off straight (σ₂/σ₁ above 1e-9) is no circle either: the radius guard.
    bow = [[x, 1e-9 * x * x, 0.0] for x in range(100)]
    with pytest.raises(scancorr.ShapeError, match=r"^circle fit: best-fit radius 5\.0+e8 mm over a point extent of "):
        shape.fit_circle(bow, min_arc_deg=0)
    # Twins on the CLI: the same words for the same points.
    for points, kw in [(line, {}), (bow, {"min_arc_deg": 0})]:
        f = straightedge / "points.txt"
        f.write_text("\n".join(" ".join(repr(float(v)) for v in p) for p in points))
        cli = cli_error(straightedge, "shape", "fit", "--kind", "circle", "--points", str(f))
        with pytest.raises(scancorr.ShapeError) as e:
            shape.fit_circle(points, **kw)
        assert cli == f"circle fit of {f}: " + str(e.value)[len("circle fit: "):]


def test_the_example_says_when_nothing_streams(tmp_path: pathlib.Path) -> None:
    ex = ROOT / "clients/python/examples/roundness.py"
    svc = Service(tmp_path)
    try:
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, str(ex), "--connect", svc.endpoint, "--timeout", "1"],
                           capture_output=True, text=True, timeout=30)
        assert time.monotonic() - t0 < 10
    finally:
        svc.stop()
    assert r.returncode == 1 and r.stdout == "", r
    assert r.stderr.splitlines() == [
        "ready",
        "error: no points on cmm/m1/corrected/points within 1 s (is machine `m1` streaming, and scancorrd "
        "serving it? `scancorr status` lists the machines served)",
    ]
    # Nothing there at all: the package's error, as the CLI words it.
    ep = f"tcp/127.0.0.1:{free_port()}"
    r = subprocess.run([sys.executable, str(ex), "--connect", ep, "--timeout", "1"], capture_output=True, text=True,
                       timeout=30)
    assert r.returncode == 1
    assert without_zenoh(r.stderr.strip()) == f"error: cannot connect to {ep}: nothing answers there {HINT}"
