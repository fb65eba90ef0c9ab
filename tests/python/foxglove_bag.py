#!/usr/bin/env python3
"""Reads the Foxglove channels of a bag `scancorr correct` wrote, independently: the Python
`mcap` package's reader and Foxglove's own published schemas (`foxglove-schemas-protobuf`),
the packed point fields read by the names, offsets and `NumericType`s each cloud declares.

    python foxglove_bag.py CORRECTED.mcap

Compares them with the bag's own corrected points (read by the project's `scancorr.read_bag`)
and with the deviation the lab defines, computed here from the bag's `scancorr.program` record:
for a bore or boss the distance in XY from the feature's nominal centre less its radius
(certified diameter, else nominal, halved), for a face the distance along its unit normal.
Lists, per Foxglove channel, the fields of its message as its schema in the bag (the
`FileDescriptorSet` of the MCAP schema record, read by protobuf's descriptor pool) declares them.
Prints one JSON document of counts and largest differences; the Rust test judges it.
"""

import json
import math
import struct
import sys

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader

import scancorr
from schema_pool import pool_of

# Foxglove's NumericType (not ROS PointField's) -> struct format.
FORMATS = {
    PackedElementField.UINT8: "<B",
    PackedElementField.INT8: "<b",
    PackedElementField.UINT16: "<H",
    PackedElementField.INT16: "<h",
    PackedElementField.UINT32: "<I",
    PackedElementField.INT32: "<i",
    PackedElementField.FLOAT32: "<f",
    PackedElementField.FLOAT64: "<d",
}


def unpack(cloud):
    """The points of a PointCloud as dicts of field -> value."""
    fields = [(f.name, f.offset, FORMATS[f.type]) for f in cloud.fields]
    n = len(cloud.data) // cloud.point_stride
    assert n * cloud.point_stride == len(cloud.data), "data is not a whole number of points"
    out = []
    for i in range(n):
        base = i * cloud.point_stride
        out.append({name: struct.unpack_from(fmt, cloud.data, base + off)[0] for name, off, fmt in fields})
    return out


def schema_fields(schema):
    """The top-level field names of the message `schema` names, from its FileDescriptorSet."""
    return sorted(f.name for f in pool_of(schema.data).FindMessageTypeByName(schema.name).fields)


def lab_deviation(feature, p):
    c = feature["nominal_center"]
    if feature["kind"] == "face":
        n = feature["normal"]
        norm = math.sqrt(sum(v * v for v in n))
        n = [v / norm for v in n]
        return sum((p[k] - c[k]) * n[k] for k in range(3))
    d = feature.get("certificate_diameter_mm") or feature["nominal_diameter_mm"]
    dx, dy = p[0] - c[0], p[1] - c[1]
    return math.sqrt(dx * dx + dy * dy) - d / 2.0


def main(path):
    clouds, logs, frames, scenes, entities = 0, 0, [], 0, []
    fox = {}  # seq -> point
    dup = 0
    types = {}
    schemas = {}
    fields = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if "/foxglove/" not in channel.topic:
                continue
            schemas[channel.topic] = [schema.name, schema.encoding, channel.message_encoding]
            if channel.topic not in fields:
                fields[channel.topic] = schema_fields(schema)
            if schema.name == "foxglove.PointCloud":
                cloud = PointCloud.FromString(message.data)
                clouds += 1
                for fl in cloud.fields:
                    types[fl.name] = PackedElementField.NumericType.Name(fl.type)
                for p in unpack(cloud):
                    if p["seq"] in fox:
                        dup += 1
                    fox[p["seq"]] = p
            elif schema.name == "foxglove.Log":
                logs += 1
                Log.FromString(message.data)
            elif schema.name == "foxglove.FrameTransform":
                t = FrameTransform.FromString(message.data)
                frames.append([t.parent_frame_id, t.child_frame_id])
            elif schema.name == "foxglove.SceneUpdate":
                scenes += 1
                u = SceneUpdate.FromString(message.data)
                entities += [e.id for e in u.entities]
    bag = scancorr.read_bag(path)
    ours = bag.points()
    program = json.loads(bag.metadata["scancorr.program"]["json"])
    features = {ft["id"]: ft for ft in program["features"]}
    seg_feature = {s["id"]: s.get("feature") for s in program["segments"]}
    missing, pos_diff, dev_diff, with_dev, want_dev, meta_diff = 0, 0.0, 0.0, 0, 0, 0
    for row in ours:
        p = fox.get(int(row["seq"]) & 0xFFFFFFFF)
        if p is None:
            missing += 1
            continue
        s = [float(v) for v in row["surface"]]
        pos_diff = max(pos_diff, *(abs(p[k] - s[i] / 1000.0) for i, k in enumerate("xyz")))
        if (
            p["calibration_version"] != int(row["calibration_version"])
            or p["segment_id"] != int(row["segment_id"])
            or bool(p["valid"]) != bool(row["valid"])
        ):
            meta_diff += 1
        fid = seg_feature.get(int(row["segment_id"]))
        if fid is not None:
            want_dev += 1
            if "deviation_mm" in p:
                with_dev += 1
                dev_diff = max(dev_diff, abs(p["deviation_mm"] - lab_deviation(features[fid], s)))
        elif "deviation_mm" in p:
            meta_diff += 1
    devs = [p["deviation_mm"] for p in fox.values() if "deviation_mm" in p]
    json.dump(
        {
            "corrected_points": len(ours),
            "foxglove_points": len(fox),
            "duplicates": dup,
            "missing": missing,
            "clouds": clouds,
            "max_position_diff_m": pos_diff,
            "max_deviation_diff_mm": dev_diff,
            "points_with_feature": want_dev,
            "points_with_deviation": with_dev,
            "deviation_range_mm": [min(devs), max(devs)] if devs else None,
            "metadata_mismatches": meta_diff,
            "field_types": types,
            "logs": logs,
            "alarms": len(bag.alarms()),
            "frames": frames,
            "scenes": scenes,
            "entities": entities,
            "features": len(features),
            "schemas": schemas,
            "message_fields": fields,
        },
        sys.stdout,
        indent=1,
        sort_keys=True,
    )
    sys.stdout.write("\n")


if __name__ == "__main__":
    main(sys.argv[1])
