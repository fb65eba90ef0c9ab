"""Fixtures: the project's binaries (`SCANCORR_BIN_DIR`, default `<repo>/target/release`), a
simulated ring measured and corrected offline, and a live scancorrd on a free loopback port.

Nothing here skips: a missing binary or a service that does not start fails the test."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import socket
import subprocess
import time
from typing import Dict, Iterator

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[3]


def binary(name: str) -> pathlib.Path:
    d = pathlib.Path(os.environ.get("SCANCORR_BIN_DIR") or ROOT / "target" / "release")
    p = d / name
    if not p.is_file():
        pytest.fail(f"{p} is missing: build it (cargo build --release) or set SCANCORR_BIN_DIR")
    return p


def run(cwd: pathlib.Path, *args: str) -> str:
    r = subprocess.run([str(binary("scancorr")), *args], cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        pytest.fail(f"scancorr {' '.join(args)}: exit {r.returncode}\n{r.stderr}")
    return r.stdout


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def ring(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, object]:
    """A ring scanned twice (CCW, CW) with a servo drift injected (two estimator alarms,
    points flagged), its true calibration, and the offline correction of it."""
    d = tmp_path_factory.mktemp("ring")
    run(d, "sim", "--program", "ring", "--fault", "servo-drift", "--out", "drift.mcap", "--calib-out", "drift.json")
    off = json.loads(run(d, "correct", "--bag", "drift.mcap", "--calib", "drift.json", "--out", "drift-off.mcap", "--json"))
    run(d, "sim", "--program", "ring", "--out", "r.mcap", "--calib-out", "v1.json", "--truth", "truth.json")
    return {"dir": d, "offline": off, "truth": json.loads((d / "truth.json").read_text())}


class Service:
    def __init__(self, d: pathlib.Path):
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.log = d / f"scancorrd-{self.port}.log"
        self.proc = subprocess.Popen(
            [str(binary("scancorrd")), "--listen", self.endpoint, "--data-dir", str(d / f"data-{self.port}")],
            cwd=d, stdout=subprocess.DEVNULL, stderr=open(self.log, "wb"),
        )
        t0 = time.monotonic()
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                break
            except OSError:
                if self.proc.poll() is not None or time.monotonic() - t0 > 20:
                    pytest.fail(f"scancorrd did not start:\n{self.log.read_text()}")
                time.sleep(0.05)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def service(tmp_path: pathlib.Path) -> Iterator[Service]:
    s = Service(tmp_path)
    yield s
    s.stop()
