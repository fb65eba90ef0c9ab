"""Receiving the corrected points and estimator alarms of one machine.

    with subscribe_points(session, "m1", classes=classes) as sub:   # subscribed on return
        for msg in sub:                                               # blocks; or sub.recv(timeout)
            ...

Key expressions (proto/scancorr/v1/scancorr.proto):
    <prefix>/<machine>/corrected/points   scancorr.v1.CorrectedPointBatch
    <prefix>/<machine>/alarms/estimator   scancorr.v1.EstimatorAlarm
"""

import queue
import time
from dataclasses import dataclass

from .descriptor import message_to_dict

POINTS_TYPE = "scancorr.v1.CorrectedPointBatch"
ALARM_TYPE = "scancorr.v1.EstimatorAlarm"


@dataclass
class Message:
    """One received message.

    kind:  "points" or "alarm"
    key:   the zenoh key expression it arrived on
    value: the decoded message as a dict (see `message_to_dict`): for "points"
           `{"points": [point, ...]}`, each point with `seq`, `t_ns`, `surface`
           (`{"x", "y", "z"}`), `calibration_version`, ...; for "alarm" the EstimatorAlarm.
    raw:   the decoded protobuf message itself
    """

    kind: str
    key: str
    value: dict
    raw: object


class DecodeError(ValueError):
    """A payload that does not decode as the message its key expression promises."""


class Subscription:
    """The subscribers of `subscribe_points`; iterable, and a context manager that
    undeclares them on exit.

    The zenoh callbacks only queue the payload bytes (an unbounded queue, so the service is
    never held up and nothing is dropped); decoding happens in `recv` / iteration.
    """

    def __init__(self, session, machine, prefix, classes, alarms):
        self.machine = machine
        self.points_key = f"{prefix}/{machine}/corrected/points"
        self.alarms_key = f"{prefix}/{machine}/alarms/estimator"
        try:
            self._types = {
                "points": classes[POINTS_TYPE],
                "alarm": classes[ALARM_TYPE],
            }
        except KeyError as e:
            raise ValueError(f"the descriptor set has no message {e}") from e
        self._queue = queue.SimpleQueue()
        self._subs = [
            session.declare_subscriber(self.points_key, self._enqueue("points")),
        ]
        if alarms:
            self._subs.append(
                session.declare_subscriber(self.alarms_key, self._enqueue("alarm"))
            )

    def _enqueue(self, kind):
        q = self._queue

        def on_sample(sample):
            q.put((kind, str(sample.key_expr), sample.payload.to_bytes()))

        return on_sample

    def recv(self, timeout=None):
        """The next message, decoded; None if none arrived within `timeout` seconds
        (`None`: wait for ever). Raises `DecodeError` on a payload that does not decode."""
        try:
            kind, key, payload = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        cls = self._types[kind]
        try:
            msg = cls.FromString(payload)
        except Exception as e:  # noqa: BLE001 - protobuf raises several types
            raise DecodeError(
                f"{key}: {len(payload)} bytes do not decode as {cls.DESCRIPTOR.full_name}: {e}"
            ) from e
        return Message(kind=kind, key=key, value=message_to_dict(msg), raw=msg)

    def __iter__(self):
        while True:
            yield self.recv()

    def messages(self, idle, first_timeout=None, deadline=None):
        """Messages until none arrived for `idle` seconds after the first one (or for
        `first_timeout` seconds before it, None: wait for ever), or until the monotonic
        time `deadline`."""
        got_one = False
        while True:
            wait = idle if got_one else first_timeout
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                wait = left if wait is None else min(wait, left)
            msg = self.recv(wait)
            if msg is None:
                return
            got_one = True
            yield msg

    def close(self):
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - session already closed
                pass
        self._subs = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def subscribe_points(session, machine, prefix="cmm", classes=None, descriptor=None, alarms=True):
    """Subscribes to the corrected points (and, with `alarms`, the estimator alarms) of
    `machine`; returns a `Subscription` that is already subscribed (so a caller can say
    "ready" once this returns) and yields `Message`s.

    The message classes come from `classes` (see `message_classes`) or are built from
    `descriptor`: a path (bag or .bin, see `load_descriptor_set`) or the descriptor set's
    bytes.
    """
    if classes is None:
        from .descriptor import load_descriptor_set, message_classes

        if descriptor is None:
            raise ValueError("subscribe_points needs `classes` or `descriptor`")
        if not isinstance(descriptor, (bytes, bytearray)):
            descriptor = load_descriptor_set(descriptor)
        classes = message_classes(bytes(descriptor))
    return Subscription(session, machine, prefix, classes, alarms)
