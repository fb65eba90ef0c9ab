#!/usr/bin/env python3
"""An independent client of the Foxglove WebSocket protocol (ws-protocol,
`foxglove.websocket.v1`) for `scancorr view`: the `websockets` package and Foxglove's published
schemas (`foxglove-schemas-protobuf`), nothing of the project.

    python foxglove_view.py PORT TOPIC EXPECTED_POINTS TIMEOUT_S [RAW_SCALE_TOPIC]

Connects to ws://127.0.0.1:PORT asking for the subprotocol, waits for `serverInfo` and the
`advertise` of TOPIC, subscribes to it (and to every other advertised channel), prints the line
`subscribed` on stderr, then collects the points of the clouds that arrive (binary frames:
opcode 1, subscription id u32, time u64, payload) until EXPECTED_POINTS or the timeout. Prints
one JSON document: the protocol facts seen and every point as [seq, x, y, z] in metres, in
arrival order. With RAW_SCALE_TOPIC (a raw scale channel, `view --raw`), its messages are decoded
with the schema the server advertised for it (a `FileDescriptorSet`, read by protobuf's own
descriptor pool) and every scale sample is listed as [seq, t_ns, x, y, z] in arrival order.
"""

import asyncio
import base64
import json
import struct
import sys

import websockets
from schema_pool import pool_of
from google.protobuf import message_factory
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

FORMATS = {PackedElementField.UINT32: "<I", PackedElementField.FLOAT64: "<d", PackedElementField.UINT8: "<B"}


def message_class(schema_b64, name):
    """The message class `name` of an advertised base64 FileDescriptorSet."""
    pool = pool_of(base64.b64decode(schema_b64))
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def scale_samples(batch):
    """[seq, t_ns, x, y, z] of a scale batch: per-sample messages or packed columns."""
    out = [[s.seq, s.t_ns, s.x, s.y, s.z] for s in batch.samples]
    c = batch.columns
    out += [list(r) for r in zip(c.seq, c.t_ns, c.x, c.y, c.z)]
    return out


async def run(port, topic, expected, timeout, raw_topic):
    out = {"subprotocol": None, "server_info": None, "channels": {}, "points": [], "other_messages": {}, "raw": []}
    raw_class = None
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"], max_size=None
    ) as ws:
        out["subprotocol"] = ws.subprotocol
        subs = {}  # subscription id -> channel
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while len(out["points"]) < expected:
            left = deadline - loop.time()
            if left <= 0:
                break
            try:
                msg = await asyncio.wait_for(ws.recv(), left)
            except asyncio.TimeoutError:
                break
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["op"] == "serverInfo":
                    out["server_info"] = m
                elif m["op"] == "advertise":
                    new = []
                    for c in m["channels"]:
                        out["channels"][c["topic"]] = {k: c[k] for k in ("id", "encoding", "schemaName", "schemaEncoding")}
                        sid = len(subs) + 100
                        if c["topic"] == raw_topic:
                            raw_class = message_class(c["schema"], c["schemaName"])
                        subs[sid] = c
                        new.append({"id": sid, "channelId": c["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    if any(c["topic"] == topic for c in m["channels"]):
                        print("subscribed", file=sys.stderr, flush=True)
                continue
            op, sid, _t = struct.unpack_from("<BIQ", msg, 0)
            if op != 1 or sid not in subs:
                out.setdefault("bad_frames", 0)
                out["bad_frames"] += 1
                continue
            ch = subs[sid]
            payload = msg[13:]
            if ch["topic"] == raw_topic:
                out["raw"] += scale_samples(raw_class.FromString(payload))
            if ch["topic"] != topic:
                out["other_messages"][ch["topic"]] = out["other_messages"].get(ch["topic"], 0) + 1
                continue
            cloud = PointCloud.FromString(payload)
            fields = {f.name: (f.offset, FORMATS[f.type]) for f in cloud.fields}
            for i in range(len(cloud.data) // cloud.point_stride):
                b = i * cloud.point_stride
                get = lambda n: struct.unpack_from(fields[n][1], cloud.data, b + fields[n][0])[0]
                out["points"].append([get("seq"), get("x"), get("y"), get("z")])
    return out


def main(argv):
    port, topic, expected, timeout = int(argv[1]), argv[2], int(argv[3]), float(argv[4])
    raw_topic = argv[5] if len(argv) > 5 else None
    out = asyncio.run(run(port, topic, expected, timeout, raw_topic))
    json.dump(out, sys.stdout)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main(sys.argv)
