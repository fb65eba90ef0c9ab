"""The scancorr bus: corrected points and alarms as numpy arrays, calibrations, status.

    import scancorr
    with scancorr.connect("tcp/127.0.0.1:7447") as bus:          # or zenoh_config="deploy/zenoh-app-tls.json5"
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
from .errors import (
    BadEndpoint,
    ConfigError,
    NoService,
    NotConnected,
    NotServed,
    Refused,
    ScancorrError,
    ServiceError,
    TlsError,
)

_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


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
    def _ask(self, selector: str, payload: Optional[bytes] = None, who: bool = False,
             machine: Optional[str] = None) -> str:
        """One query; the reply text, or `ServiceError` with the service's message. The
        route to the queryable may take a moment after connecting: retried for
        `query_timeout` seconds. Then `Refused` when `machine` is seen served (its scancorrd's
        liveliness token answers: the query was dropped on its way, as a router's access
        control drops a denied query), else `NoService`."""
        t0 = time.monotonic()
        while True:
            left = self.query_timeout - (time.monotonic() - t0)
            kw: Dict[str, Any] = {"timeout": min(3.0, max(left, 0.5))}
            if payload is not None:
                kw["payload"] = payload
            if who:
                kw["attachment"] = _requester(self.session)
            for reply in self.session.get(selector, **kw):
                if reply.ok is not None:
                    return reply.ok.payload.to_string()
                err = reply.err
                msg = err.payload.to_string() if err is not None else "error"
                raise ServiceError(msg)
            if time.monotonic() - t0 > self.query_timeout:
                if machine is not None and self._served(machine):
                    raise Refused(
                        f"no answer on `{selector}` although scancorrd serves machine `{machine}` "
                        f"(its liveliness token `{self.prefix}/{machine}/scancorrd` is seen): the query "
                        "was refused on its way: a router's access control drops a denied query "
                        "without telling the asker (check its rules for this session's certificate "
                        "role, deploy/router.json5)"
                    )
                raise NoService(
                    f"no scancorrd answered on `{selector}` (is it running, reachable and serving this prefix?)"
                )
            time.sleep(0.25)

    def _served(self, machine: str, timeout: float = 1.0) -> bool:
        """Whether a scancorrd's liveliness token for `machine` is seen."""
        try:
            replies = self.session.liveliness().get(self._key(machine, "scancorrd"), timeout=timeout)
            return any(r.ok is not None for r in replies)
        except Exception:  # a session closed meanwhile: not seen
            return False

    def _json(self, selector: str, payload: Optional[bytes] = None, who: bool = False,
              machine: Optional[str] = None) -> Any:
        text = self._ask(selector, payload, who, machine)
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
        return self._json(key, machine=machine)

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
        return self._json(self._key(machine, "calibration/write"), json.dumps(doc).encode(), who=True,
                          machine=machine)

    def rollback(self, machine: str, to: int) -> Dict[str, Any]:
        """Makes version `to` of `machine`'s calibration current again, as a new version
        (its parent the current one). Returns `{"machine", "version", "parent_version"}`."""
        if not isinstance(to, int) or isinstance(to, bool) or to < 1:
            raise ValueError(f"to {to!r}: must be a version number (>= 1)")
        return self._json(f"{self._key(machine, 'calibration/write')}?rollback={to}", who=True, machine=machine)

    def history(self, machine: str) -> List[Dict[str, Any]]:
        """Every stored version of `machine`'s calibration, oldest first."""
        return self._json(f"{self._key(machine, 'calibration')}?history", machine=machine)

    def status(self, machine: str) -> Dict[str, Any]:
        """`machine`'s status document; `NotServed` when the service does not serve it."""
        v = self._json(self._key(machine, "status"), machine=machine)
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


def _requester(session: Any = None) -> str:
    """`user@host; zid=<this session's zenoh id>`, for the service's audit trail (as the CLI
    sends it; the user is never made up: the login name, else `uid N`)."""
    import getpass
    import os
    import socket

    try:
        user = getpass.getuser()
    except Exception:
        user = f"uid {os.getuid()}" if hasattr(os, "getuid") else ""
    who = f"{user}@{socket.gethostname()}"
    zid = None
    try:
        zid = str(session.info.zid()) if session is not None else None
    except Exception:
        try:
            zid = str(session.zid())
        except Exception:
            zid = None
    return f"{who}; zid={zid}" if zid else who


def _looks_like_json(doc: Union[str, bytes]) -> bool:
    s = doc.lstrip()[:1]
    return s in ("{", b"{")


#: Zenoh's link protocols (as the `scancorr` CLI lists them).
PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock", "quic_datagram")

#: The TLS files a zenoh configuration may name (under `transport/link/tls/`).
TLS_FILES = ("root_ca_certificate", "connect_certificate", "connect_private_key",
             "listen_certificate", "listen_private_key")

_HINT = "is scancorrd or a zenoh router running and listening on it?"


def _shown(text: object) -> str:
    """A name from outside, quoted, escaped and cut to 40 characters (as the CLI shows it)."""
    t = str(text)
    s = t[:40] + ("…" if len(t) > 40 else "")
    return json.dumps(s, ensure_ascii=False)


def _one_line(text: object) -> str:
    """A zenoh error on one line, without the source location zenoh appends."""
    s = str(text)
    i = s.rfind(" at /")
    if i >= 0 and s.rstrip().endswith("."):
        s = s[:i]
    s = " ".join(s.split())
    return s if len(s) <= 300 else s[:300] + "…"


def check_endpoint(endpoint: object) -> str:
    """Returns `endpoint` when it is `PROTOCOL/ADDRESS` with a protocol zenoh knows; raises
    `BadEndpoint` with the words of `scancorr --connect` otherwise."""
    if not isinstance(endpoint, str):
        raise BadEndpoint(f"endpoint {endpoint!r}: must be a string, e.g. tcp/127.0.0.1:7447", endpoint)
    shown = _shown(endpoint)
    proto, sep, addr = endpoint.partition("/")
    if sep and proto in PROTOCOLS:
        if not addr or addr[0] in "?#":
            raise BadEndpoint(
                f"endpoint {shown}: no address after `{proto}/`; use {proto}/HOST:PORT, e.g. tcp/127.0.0.1:7447",
                endpoint,
            )
        return endpoint
    if sep:
        raise BadEndpoint(
            f"endpoint {shown}: unknown protocol `{proto}` (zenoh knows {', '.join(PROTOCOLS)}); "
            "use tcp/HOST:PORT, e.g. tcp/127.0.0.1:7447",
            endpoint,
        )
    example = endpoint if ":" in endpoint else "127.0.0.1:7447"
    raise BadEndpoint(f"endpoint {shown}: an endpoint names its protocol; use tcp/HOST:PORT, e.g. tcp/{example}",
                      endpoint)


def _conf_value(conf: Any, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # absent key, or not JSON
        return None


def _file_endpoints(conf: Any) -> List[str]:
    """The configuration's `connect/endpoints`: a list, or per-mode lists."""
    v = _conf_value(conf, "connect/endpoints")
    if isinstance(v, dict):
        mode = _conf_value(conf, "mode") or "peer"
        v = v.get(mode, [])
    return [e for e in v if isinstance(e, str)] if isinstance(v, list) else []


def _check_tls_files(conf: Any, source: str) -> None:
    """Each TLS certificate and key the configuration names must be a readable file."""
    for name in TLS_FILES:
        key = f"transport/link/tls/{name}"
        path = _conf_value(conf, key)
        if not isinstance(path, str) or not path:
            continue
        try:
            with open(path, "rb") as f:
                f.read(1)
        except OSError as e:
            why = e.strerror or str(e)
            raise TlsError(
                f"{source}: `{key}`: cannot read the TLS certificate or key file {path}: {why}",
                key, path,
            ) from None


def _listening(endpoint: str, timeout: float = 0.5) -> bool:
    """Whether a TCP connection to the endpoint's HOST:PORT is accepted (tcp, tls, ws, quic
    endpoints; False for others)."""
    import socket

    proto, _, addr = endpoint.partition("/")
    if proto not in ("tcp", "tls", "ws"):
        return False
    addr = re.split(r"[?#]", addr, maxsplit=1)[0]
    host, _, port = addr.rpartition(":")
    host = host.strip("[]")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
        return True
    except (OSError, ValueError):
        return False


def connect(endpoint: Union[str, Sequence[str], None] = None, *,
            zenoh_config: Union[str, "PathLike[str]", None] = None,
            prefix: str = "cmm", mode: Optional[str] = None,
            query_timeout: float = 6.0, timeout: float = 3.0) -> Client:
    """Opens a session to the scancorr bus and checks that something answers.

    endpoint:     zenoh endpoint(s) to connect to, e.g. `"tcp/127.0.0.1:7447"`
    zenoh_config: a zenoh configuration file (JSON5), as zenoh's own tools take one — how a
                  TLS deployment is reached (`deploy/`: certificates, mode `client`)
    mode:         `peer` (the default without a file) or `client`
    timeout:      seconds to wait for a zenoh session at the endpoint(s)
    Multicast scouting is off unless the file turns it on: endpoints are given explicitly.

    Raises, with the words of the `scancorr` CLI: `BadEndpoint` (not PROTOCOL/HOST:PORT),
    `ConfigError` (a file that does not load), `TlsError` (a certificate or key it names is
    missing or unreadable: the key and the path), `NotConnected` (nothing answers there
    within `timeout`), `Refused` (something listens there but no zenoh session was
    established: e.g. the router refused the TLS handshake).
    """
    import zenoh

    if endpoint is None and zenoh_config is None:
        raise BadEndpoint("connect: give an endpoint (e.g. 'tcp/127.0.0.1:7447') or zenoh_config=FILE")
    check_prefix(prefix)
    if not (isinstance(timeout, (int, float)) and timeout > 0):
        raise ValueError(f"timeout {timeout!r}: must be a positive number of seconds")
    eps: Optional[List[str]] = None
    if endpoint is not None:
        eps = [endpoint] if isinstance(endpoint, str) else list(endpoint)
        if not eps:
            raise BadEndpoint("connect: an empty list of endpoints; give e.g. 'tcp/127.0.0.1:7447'")
        for e in eps:
            check_endpoint(e)
    if zenoh_config is not None:
        source = f"zenoh configuration {zenoh_config}"
        try:
            conf = zenoh.Config.from_file(str(zenoh_config))
        except Exception as e:
            raise ConfigError(f"{source}: {_one_line(e)}") from None
    else:
        source = "connect"
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("mode", json.dumps(mode or "peer"))
    if mode is not None and zenoh_config is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if eps is not None:
        try:
            conf.insert_json5("connect/endpoints", json.dumps(eps))
        except Exception as e:
            raise BadEndpoint(f"endpoint {_shown(', '.join(eps))}: {_one_line(e)}", endpoint) from None
    else:
        eps = _file_endpoints(conf)
        for e in eps:
            try:
                check_endpoint(e)
            except BadEndpoint as b:
                raise BadEndpoint(f"{source}: {b}", e) from None
    _check_tls_files(conf, source)
    # Fail when no endpoint answers within `timeout` (zenoh retries until then), instead of
    # a session that retries in the background while every call finds nothing.
    conf.insert_json5("connect/timeout_ms", json.dumps(int(timeout * 1000)))
    conf.insert_json5("connect/exit_on_failure", "true")
    where = ", ".join(eps) if eps else "the configuration's endpoints (it names none)"
    try:
        session = zenoh.open(conf)
    except Exception as e:
        raise _open_error(eps, where, _one_line(e)) from None
    # Something must answer: a peer or a router (with no endpoint to connect to, one found by
    # scouting).
    deadline = time.monotonic() + timeout
    while not (list(session.info.peers_zid()) or list(session.info.routers_zid())):
        if time.monotonic() > deadline:
            try:
                session.close()
            except Exception:
                pass
            raise _open_error(eps, where, f"no zenoh peer or router within {timeout:g} s")
        time.sleep(0.02)
    return Client(session, prefix=prefix, query_timeout=query_timeout)


def _open_error(eps: List[str], where: str, why: str) -> ScancorrError:
    """`Refused` when something accepts TCP connections at an endpoint (no zenoh session was
    established there), else `NotConnected`."""
    listening = [e for e in eps if _listening(e)]
    if listening:
        return Refused(
            f"cannot connect to {where}: something listens at {', '.join(listening)} but no zenoh session "
            "was established (for tls/: the router refused the TLS handshake — a certificate it does not "
            f"accept, or none; or no zenoh there) [zenoh: {why}]"
        )
    return NotConnected(f"cannot connect to {where}: nothing answers there ({_HINT}) [zenoh: {why}]", eps)
