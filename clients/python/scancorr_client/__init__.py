"""A small Python client for the scancorr bus (zenoh + protobuf).

    from scancorr_client import load_descriptor_set, message_classes, open_session, subscribe_points

See README.md beside this package. Only `protobuf` is needed to import it; `eclipse-zenoh`
is imported when a session is opened, `mcap` when a descriptor set is read from a bag.
"""

from .descriptor import (
    build_pool,
    load_descriptor_set,
    message_classes,
    message_to_dict,
)
from .points import Message, Subscription, subscribe_points
from .session import open_session

__all__ = [
    "Message",
    "Subscription",
    "build_pool",
    "load_descriptor_set",
    "message_classes",
    "message_to_dict",
    "open_session",
    "subscribe_points",
]
