"""scancorr: corrected CMM scanning points, calibrations and shape fits from Python.

    import scancorr
    with scancorr.connect("tcp/127.0.0.1:7447") as bus:
        with bus.subscribe_points("m1") as sub:
            for batch in sub.batches(idle=5):
                print(len(batch.points), batch.points["surface"][0], sub.missed)

- `connect(endpoint | zenoh_config=FILE, timeout=3)` → `Client` (something answered, or
  `NotConnected` / `Refused` / `BadEndpoint` / `TlsError`): `subscribe_points`,
  `subscribe_alarms`, `get_calibration`, `put_calibration`, `history`, `status`, `machines`
- `read_bag(path, skip_damaged=False)` → `Bag`: every channel as numpy arrays (pandas with
  `Bag.frames()`), every checksum verified: damage raises `BagError`; a bag cut short, skipped
  chunks and undecodable messages are counted on the `Bag` and warned about (`BagWarning`)
- `scancorr.shape`: `fit_circle`, `fit_sphere`, `fit_line`, `fit_plane`, `roundness`,
  `straightness`
- errors: every one a `ScancorrError` (`scancorr.errors` draws the tree), worded as the
  `scancorr` CLI words the same case
- `POINT_DTYPE`, `ALARM_DTYPE`: the arrays' layouts (`scancorr.arrays`)
"""

from . import arrays, errors, shape
from .arrays import ALARM_DTYPE, POINT_DTYPE, DecodeError
from .bag import Bag, BagError, BagWarning, Channel, DamagedChunk, Truncation, read_bag
from .client import AlarmSubscription, Client, PointBatch, PointSubscription, connect
from .errors import (
    BadEndpoint,
    ConfigError,
    NoService,
    NotConnected,
    NotServed,
    Refused,
    ScancorrError,
    ServiceError,
    ShapeError,
    TlsError,
)

__version__ = "0.1.0"

__all__ = [
    "ALARM_DTYPE",
    "POINT_DTYPE",
    "AlarmSubscription",
    "BadEndpoint",
    "Bag",
    "BagError",
    "BagWarning",
    "Channel",
    "Client",
    "ConfigError",
    "DamagedChunk",
    "DecodeError",
    "NoService",
    "NotConnected",
    "NotServed",
    "PointBatch",
    "PointSubscription",
    "Refused",
    "ScancorrError",
    "ServiceError",
    "ShapeError",
    "TlsError",
    "Truncation",
    "arrays",
    "connect",
    "errors",
    "read_bag",
    "shape",
]
