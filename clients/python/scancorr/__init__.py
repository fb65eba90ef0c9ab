"""scancorr: corrected CMM scanning points, calibrations and shape fits from Python.

    import scancorr
    with scancorr.connect("tcp/127.0.0.1:7447") as bus:
        with bus.subscribe_points("m1") as sub:
            for batch in sub.batches(idle=5):
                print(len(batch.points), batch.points["surface"][0], sub.missed)

- `connect(endpoint | zenoh_config=FILE)` → `Client`: `subscribe_points`, `subscribe_alarms`,
  `get_calibration`, `put_calibration`, `history`, `status`, `machines`
- `read_bag(path, skip_damaged=False)` → `Bag`: every channel as numpy arrays (pandas with
  `Bag.frames()`), every checksum verified: damage raises `BagError`; a bag cut short, skipped
  chunks and undecodable messages are counted on the `Bag` and warned about (`BagWarning`)
- `scancorr.shape`: `fit_circle`, `fit_sphere`, `fit_line`, `fit_plane`, `roundness`,
  `straightness`
- `POINT_DTYPE`, `ALARM_DTYPE`: the arrays' layouts (`scancorr.arrays`)
"""

from . import arrays, shape
from .arrays import ALARM_DTYPE, POINT_DTYPE, DecodeError
from .bag import Bag, BagError, BagWarning, Channel, DamagedChunk, Truncation, read_bag
from .client import (
    AlarmSubscription,
    Client,
    NoService,
    NotServed,
    PointBatch,
    PointSubscription,
    ScancorrError,
    ServiceError,
    connect,
)

__version__ = "0.1.0"

__all__ = [
    "ALARM_DTYPE",
    "POINT_DTYPE",
    "AlarmSubscription",
    "Bag",
    "BagError",
    "BagWarning",
    "Channel",
    "Client",
    "DamagedChunk",
    "DecodeError",
    "NoService",
    "NotServed",
    "PointBatch",
    "PointSubscription",
    "ScancorrError",
    "ServiceError",
    "Truncation",
    "arrays",
    "connect",
    "read_bag",
    "shape",
]
