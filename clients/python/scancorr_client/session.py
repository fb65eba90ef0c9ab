"""Opening a zenoh session to scancorrd the way the project's own tools do."""

import json


def open_session(connect, mode="peer", listen=(), multicast_scouting=False):
    """A `zenoh.Session` connected to the endpoints `connect` (e.g. `["tcp/127.0.0.1:7447"]`).

    `mode` is "peer" (the default, like the `scancorr` CLI) or "client" (for a router).
    Multicast scouting is off unless asked for: the endpoints are given explicitly, so
    nothing else on the network is joined by accident. Close it with `.close()` or use it as
    a context manager.
    """
    import zenoh

    if isinstance(connect, str):
        connect = [connect]
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    return zenoh.open(conf)
