"""The scancorr bus: corrected points and alarms as numpy arrays, calibrations, status.

    import scancorr
    with scancorr.connect("tcp/127.0.0.1:7447") as bus:          # or zenoh_config="app.json5"
        with bus.subscribe_points("m1") as sub:
            for batch in sub.batches(idle=5):
                print(batch.points["surface"].mean(axis=0), sub.missed)

Key expressions (proto/scancorr/v1/scancorr.proto; `prefix` defaults to `cmm`):

    <prefix>/<machine>/corrected/points   CorrectedPointBatch   (subscribe_points)
    <prefix>/<machine>/alarms/estimator   EstimatorAlarm        (subscribe_alarms)
    <prefix>/<machine>/calibration        queryable: get (?version=N, ?history)
    <prefix>/<machine>/calibration/write  queryable: put (payload) and ?rollback=N
    <prefix>/<machine>/status             queryable: the machine's status document
    <prefix>/<machine>/scancorrd          liveliness token of the service serving it

Machine ids and the prefix are checked (1–64 characters of A–Z a–z 0–9 _ - .) before they
become part of a key expression.
"""

from __future__ import annotations

import json
import queue
import re
import threading
import time
from dataclasses import dataclass, field
from os import PathLike
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Union

import numpy as np

from . import arrays

_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class ScancorrError(RuntimeError):
    """Base of this package's errors."""


class ServiceError(ScancorrError):
    """The service refused a request; the message is the service's own."""


class NotServed(ServiceError):
    """The service does not serve the machine asked about."""


class NoService(ScancorrError, TimeoutError):
    """No scancorrd answered (not running, not reachable, or serving another prefix)."""


def check_name(what: str, name: str) -> str:
    """Returns `name` when it is a valid machine id (or prefix chunk); raises `ValueError`
    naming `what` otherwise."""
    if not isinstance(name, str) or not _NAME.match(name):
        shown = repr(name)[:80]
        raise ValueError(
            f"{what} {shown}: must be 1–64 characters of A–Z a–z 0–9 _ - . (it becomes part of a key expression)"
        )
    return name


def check_prefix(prefix: str) -> str:
    """Returns `prefix` when every `/`-separated chunk is a valid name (at most 128 bytes)."""
    if not isinstance(prefix, str) or len(prefix) > 128:
        raise ValueError(f"prefix {repr(prefix)[:80]}: at most 128 characters")
    for chunk in prefix.split("/"):
        check_name("prefix chunk", chunk)
    return prefix


@dataclass
class PointBatch:
    """One batch of corrected points as it arrived.

    points:    `arrays.POINT_DTYPE` array
    key:       the key expression it arrived on
    missed:    points missed just before this batch (a gap in `seq`), 0 normally
    breakdown: per-effect corrections (effect id → (n, 3) array, mm) when asked for
    """

    points: np.ndarray
    key: str
    missed: int = 0
    breakdown: Optional[Dict[str, np.ndarray]] = None


class _Subscription:
    """Zenoh's callback only queues the payload bytes (an unbounded queue: the service is
    never held up and nothing is dropped); decoding happens in the caller's thread, or in the
    subscription's own thread when a callback was given."""

    def __init__(self, session: Any, keys: Sequence[str], callback: Optional[Callable[[Any], None]]):
        self._queue: "queue.SimpleQueue[tuple]" = queue.SimpleQueue()
        self._subs = []
        self._closed = False
        self.errors: List[BaseException] = []
        q = self._queue

        def on_sample(sample: Any) -> None:
            q.put((str(sample.key_expr), sample.payload.to_bytes()))

        for k in keys:
            self._subs.append(session.declare_subscriber(k, on_sample))
        self._thread = None
        if callback is not None:
            self._thread = threading.Thread(target=self._pump, args=(callback,), daemon=True)
            self._thread.start()

    def _decode(self, key: str, data: bytes) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    def _pump(self, callback: Callable[[Any], None]) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                callback(self._decode(*item))
            except BaseException as e:  # kept for the caller, never lost silently
                self.errors.append(e)

    def recv(self, timeout: Optional[float] = None) -> Any:
        """The next item, decoded; None when nothing arrived within `timeout` seconds (None:
        wait for ever). Raises `arrays.DecodeError` for a payload that does not decode."""
        if self._thread is not None:
            raise ScancorrError("this subscription hands its items to its callback")
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        if item is None:
            return None
        return self._decode(*item)

    def batches(self, idle: Optional[float] = None, first_timeout: Optional[float] = None,
                deadline: Optional[float] = None) -> Iterator[Any]:
        """Items until none arrived for `idle` seconds after the first (or `first_timeout`
        before it; None: wait for ever), or until the monotonic time `deadline`."""
        got = False
        while True:
            wait = idle if got else first_timeout
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                wait = left if wait is None else min(wait, left)
            item = self.recv(wait)
            if item is None:
                return
            got = True
            yield item

    def __iter__(self) -> Iterator[Any]:
        while not self._closed:
            item = self.recv()
            if item is None:
                return
            yield item

    def pending(self) -> int:
        """Payloads received and not yet decoded."""
        return self._queue.qsize()

    def close(self) -> None:
        """Undeclares the subscribers; a callback thread finishes what was queued first."""
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # session already closed
                pass
        self._subs = []
        self._closed = True
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> "_Subscription":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class PointSubscription(_Subscription):
    """Corrected points of one machine, one `PointBatch` per message. `missed` counts the
    points missed in all (gaps in `seq`), `received` the points received."""

    def __init__(self, session: Any, key: str, breakdown: bool, callback: Optional[Callable[[PointBatch], None]]):
        self.key = key
        self.breakdown = breakdown
        self.missed = 0
        self.received = 0
        self._next: Optional[int] = None
        super().__init__(session, [key], callback)

    def _decode(self, key: str, data: bytes) -> PointBatch:
        if self.breakdown:
            pts, br = arrays.decode_breakdown(data, key)
        else:
            pts, br = arrays.decode_points(data, key), None
        missed = 0
        if len(pts):
            first = int(pts["seq"][0])
            if self._next is not None and first > self._next:
                missed = first - self._next
            # Gaps inside a batch (the service never makes them, but count what is seen).
            d = np.diff(pts["seq"].astype(np.int64))
            missed += int(np.clip(d - 1, 0, None).sum())
            self._next = int(pts["seq"][-1]) + 1
        self.missed += missed
        self.received += len(pts)
        return PointBatch(points=pts, key=key, missed=missed, breakdown=br)


class AlarmSubscription(_Subscription):
    """Estimator-validity alarms of one machine, one `arrays.ALARM_DTYPE` row per message."""

    def __init__(self, session: Any, key: str, callback: Optional[Callable[[np.ndarray], None]]):
        self.key = key
        super().__init__(session, [key], callback)

    def _decode(self, key: str, data: bytes) -> np.ndarray:
        return arrays.decode_alarm(data, key)


class Client:
    """A zenoh session to the scancorr bus (see `connect`)."""

    def __init__(self, session: Any, prefix: str = "cmm", query_timeout: float = 6.0):
        self.session = session
        self.prefix = check_prefix(prefix)
        self.query_timeout = query_timeout

    # -- keys
    def _key(self, machine: str, suffix: str) -> str:
        return f"{self.prefix}/{check_name('machine id', machine)}/{suffix}"

    # -- streams
    def subscribe_points(self, machine: str, *, breakdown: bool = False,
                         callback: Optional[Callable[[PointBatch], None]] = None) -> PointSubscription:
        """Subscribes to `machine`'s corrected points; subscribed on return. Without
        `callback`: iterate, or call `recv(timeout)` / `batches(idle=…)`. With it: each
        `PointBatch` is handed to `callback` on the subscription's own thread (exceptions it
        raises are kept in `.errors`). `breakdown=True` adds the per-effect corrections."""
        return PointSubscription(self.session, self._key(machine, "corrected/points"), breakdown, callback)

    def subscribe_alarms(self, machine: str, *,
                         callback: Optional[Callable[[np.ndarray], None]] = None) -> AlarmSubscription:
        """Subscribes to `machine`'s estimator-validity alarms (as `subscribe_points`)."""
        return AlarmSubscription(self.session, self._key(machine, "alarms/estimator"), callback)

    # -- queries
    def _ask(self, selector: str, payload: Optional[bytes] = None, who: bool = False) -> str:
        """One query; the reply text, or `ServiceError` with the service's message. The
        route to the queryable may take a moment after connecting: retried for
        `query_timeout` seconds before `NoService`."""
        t0 = time.monotonic()
        while True:
            kw: Dict[str, Any] = {"timeout": 3.0}
            if payload is not None:
                kw["payload"] = payload
            if who:
                kw["attachment"] = _requester()
            for reply in self.session.get(selector, **kw):
                if reply.ok is not None:
                    return reply.ok.payload.to_string()
                err = reply.err
                msg = err.payload.to_string() if err is not None else "error"
                raise ServiceError(msg)
            if time.monotonic() - t0 > self.query_timeout:
                raise NoService(
                    f"no scancorrd answered on `{selector}` (is it running, reachable and serving prefix `{self.prefix}`?)"
                )
            time.sleep(0.25)

    def _json(self, selector: str, payload: Optional[bytes] = None, who: bool = False) -> Any:
        text = self._ask(selector, payload, who)
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise ServiceError(f"`{selector}`: the reply is not JSON ({e}): {text[:200]}") from e

    def get_calibration(self, machine: str, version: Optional[int] = None) -> Dict[str, Any]:
        """The current calibration document of `machine` (or version `version`)."""
        key = self._key(machine, "calibration")
        if version is not None:
            if not isinstance(version, int) or isinstance(version, bool) or version < 0:
                raise ValueError(f"version {version!r}: must be a non-negative integer")
            key = f"{key}?version={version}"
        return self._json(key)

    def put_calibration(self, machine: str, doc: Union[Dict[str, Any], str, bytes, "PathLike[str]"],
                        note: Optional[str] = None) -> Dict[str, Any]:
        """Stores `doc` (a calibration document: dict, JSON text, or a path to a JSON file)
        as `machine`'s new current version; `note` replaces its note. Returns
        `{"machine", "version", "parent_version"}`. The service checks the document and
        refuses it with its reason (`ServiceError`)."""
        if isinstance(doc, (str, bytes)) and not _looks_like_json(doc):
            doc = open(doc, "rb").read()  # a path given as text
        elif isinstance(doc, PathLike):
            doc = open(doc, "rb").read()
        if isinstance(doc, (str, bytes)):
            try:
                doc = json.loads(doc)
            except json.JSONDecodeError as e:
                raise ValueError(f"the calibration document is not JSON: {e}") from e
        if not isinstance(doc, dict):
            raise ValueError("the calibration document must be a JSON object")
        if note is not None:
            doc = dict(doc, note=note)
        return self._json(self._key(machine, "calibration/write"), json.dumps(doc).encode(), who=True)

    def rollback(self, machine: str, to: int) -> Dict[str, Any]:
        """Makes version `to` of `machine`'s calibration current again, as a new version
        (its parent the current one). Returns `{"machine", "version", "parent_version"}`."""
        if not isinstance(to, int) or isinstance(to, bool) or to < 1:
            raise ValueError(f"to {to!r}: must be a version number (>= 1)")
        return self._json(f"{self._key(machine, 'calibration/write')}?rollback={to}", who=True)

    def history(self, machine: str) -> List[Dict[str, Any]]:
        """Every stored version of `machine`'s calibration, oldest first."""
        return self._json(f"{self._key(machine, 'calibration')}?history")

    def status(self, machine: str) -> Dict[str, Any]:
        """`machine`'s status document; `NotServed` when the service does not serve it."""
        v = self._json(self._key(machine, "status"))
        if isinstance(v, dict) and v.get("served") is False:
            raise NotServed(
                f"scancorrd does not serve machine `{machine}` (no calibration stored for it and no samples accepted); put a calibration to start serving it"
            )
        return v

    def machines(self, timeout: float = 3.0) -> List[str]:
        """The machines served on the bus (each scancorrd declares a liveliness token per
        machine it serves), sorted."""
        out = set()
        head, tail = f"{self.prefix}/", "/scancorrd"
        for reply in self.session.liveliness().get(f"{self.prefix}/*/scancorrd", timeout=timeout):
            if reply.ok is not None:
                k = str(reply.ok.key_expr)
                if k.startswith(head) and k.endswith(tail):
                    out.add(k[len(head):-len(tail)])
        return sorted(out)

    def close(self) -> None:
        try:
            self.session.close()
        except Exception:
            pass

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _requester() -> str:
    """`user@host`, for the service's audit trail."""
    import getpass
    import socket

    try:
        user = getpass.getuser()
    except Exception:
        user = "unknown"
    return f"{user}@{socket.gethostname()}"


def _looks_like_json(doc: Union[str, bytes]) -> bool:
    s = doc.lstrip()[:1]
    return s in ("{", b"{")


def connect(endpoint: Union[str, Sequence[str], None] = None, *,
            zenoh_config: Union[str, "PathLike[str]", None] = None,
            prefix: str = "cmm", mode: Optional[str] = None,
            query_timeout: float = 6.0) -> Client:
    """Opens a session to the scancorr bus.

    endpoint:     zenoh endpoint(s) to connect to, e.g. `"tcp/127.0.0.1:7447"`
    zenoh_config: a zenoh configuration file (JSON5), as zenoh's own tools take one — how a
                  TLS deployment is reached (`deploy/`: certificates, mode `client`)
    mode:         `peer` (the default without a file, like the `scancorr` CLI) or `client`
    Multicast scouting is off unless the file turns it on: endpoints are given explicitly.
    """
    import zenoh

    if zenoh_config is not None:
        try:
            conf = zenoh.Config.from_file(str(zenoh_config))
        except Exception as e:
            raise ValueError(f"zenoh configuration {zenoh_config}: {e}") from e
    else:
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("mode", json.dumps(mode or "peer"))
    if mode is not None and zenoh_config is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if endpoint is not None:
        eps = [endpoint] if isinstance(endpoint, str) else list(endpoint)
        conf.insert_json5("connect/endpoints", json.dumps(eps))
    if endpoint is None and zenoh_config is None:
        raise ValueError("connect: give an endpoint (e.g. 'tcp/127.0.0.1:7447') or zenoh_config=FILE")
    return Client(zenoh.open(conf), prefix=prefix, query_timeout=query_timeout)
