#!/usr/bin/env python3
"""Independent reader of scancorr bags: the `mcap` package's reader plus `google.protobuf`.

Nothing of the project is used: message classes are built at run time from the
FileDescriptorSet each channel carries as its schema data, so this checks that a bag is
self-describing to any MCAP/protobuf consumer.

    python read_bag.py BAG.mcap

Prints one JSON document on stdout:

    {
      "file": ..., "profile": ..., "library": ...,
      "topics": {
        "<prefix>/<machine>/raw/scale": {
          "schema": "scancorr.v1.ScaleBatch", "schema_encoding": "protobuf",
          "message_encoding": "protobuf", "machine": "m1",
          "messages": N,          # MCAP messages (batches)
          "samples": N,           # samples/points summed over batches; 1 per other message
          "first_t_ns": ..., "last_t_ns": ...,   # of the first/last sample in file order
          "first_seq": ..., "last_seq": ...
        }, ...
      },
      "metadata": {"<record name>": [{entries}, ...], ...}   # every record, in file order
    }

and checks, for every channel: schema and message encodings are protobuf, the schema's
descriptor set builds and holds the schema's message, every message decodes, every sample's
`machine_id` is the topic's machine, `seq` is consecutive per topic, the message counts agree
with the file's statistics and the sample counts with the `scancorr.sample_counts` metadata
record when the bag has one. Any problem: the problems go to stderr and the exit code is 1
(the JSON is still printed); a bag that cannot be read at all exits 2.
"""

import json
import sys
from types import SimpleNamespace

try:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader
except ImportError as e:  # pragma: no cover - environment problem
    sys.exit(
        f"read_bag.py: {e}: run with the interpreter printed by scripts/python-env.sh "
        "(it installs tests/python/requirements.txt)"
    )

# Repeated fields that hold the samples of a batch message. Any other message counts as one.
BATCH_FIELDS = ("samples", "points")
# Schemas of the Foxglove channels `scancorr correct` writes beside scancorr's (no batches).
FOXGLOVE_SCHEMAS = ("foxglove.", "scancorr.foxglove.")
MAX_PROBLEMS_SHOWN = 50


class Problems:
    def __init__(self):
        self.items = []

    def add(self, msg):
        self.items.append(msg)


def build_pool(fds_bytes):
    """A DescriptorPool holding every file of a serialized FileDescriptorSet."""
    fds = descriptor_pb2.FileDescriptorSet()
    fds.ParseFromString(fds_bytes)
    files = {f.name: f for f in fds.file}
    pool = descriptor_pool.DescriptorPool()
    added = set()

    def add(name, stack=()):
        if name in added:
            return
        if name in stack:
            raise ValueError(f"import cycle through {name}")
        f = files.get(name)
        if f is None:
            raise ValueError(f"descriptor set lacks imported file {name}")
        for dep in f.dependency:
            add(dep, stack + (name,))
        pool.Add(f)
        added.add(name)

    for name in files:
        add(name)
    return pool, sorted(files)


def column_samples(columns, sample_desc, where, problems):
    """The samples of a packed batch (scancorr.v1.3) or of one packed block of points
    (scancorr.v1.4): the columns message numbers its fields as the sample does, each a column
    of one value per sample, except `machine_id`, once. A sample's vector field `v` is packed as
    columns `v_x`, `v_y`, `v_z`; columns the sample has no field for (a block's effects and
    corrections) are left to the reader of that message."""
    sample_fields = sample_desc.fields_by_name
    names = [
        f.name
        for f in columns.DESCRIPTOR.fields
        if f.name != "machine_id"
        and (f.name in sample_fields or f.name.rpartition("_")[0] in sample_fields)
    ]
    cols = {name: list(getattr(columns, name)) for name in names}
    n = len(cols["seq"])

    def optional(name):
        # A proto3 `optional` field of the sample (scancorr.v1.5's probing force): its
        # column is empty when no sample of the batch has it.
        f = sample_fields.get(name)
        oneof = f.containing_oneof if f is not None else None
        return oneof is not None and oneof.name.startswith("_")

    for name in [k for k, col in cols.items() if not col and n and optional(k)]:
        del cols[name]
        names.remove(name)
    for name, col in cols.items():
        if len(col) != n:
            problems.add(f"{where}: column {name} holds {len(col)} values for {n} samples")
            return []
    # A block of points (v1.4) holds its corrections as columns of one value per point and
    # effect, point-major.
    effects = list(getattr(columns, "effects", []))
    for name in ("correction_dx", "correction_dy", "correction_dz"):
        if name in columns.DESCRIPTOR.fields_by_name:
            got = len(getattr(columns, name))
            if got != n * len(effects):
                problems.add(
                    f"{where}: column {name} holds {got} values for {n} points x {len(effects)} effects"
                )
                return []
    scalars = [name for name in names if name in sample_fields]
    return [
        SimpleNamespace(machine_id=columns.machine_id, **{k: cols[k][i] for k in scalars})
        for i in range(n)
    ]


def machine_of(topic):
    """`<prefix>/<machine>/<group>/<stream>` -> machine (None if the topic has another shape)."""
    parts = topic.split("/")
    return parts[-3] if len(parts) >= 4 else None


def read(path, problems):
    topics = {}
    classes = {}  # schema id -> message class
    streams = {}  # topic -> state
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
        if summary is None:
            problems.add("bag has no summary section (not closed cleanly?)")

        def topic_entry(schema, channel):
            t = topics.get(channel.topic)
            if t is not None:
                return t
            t = topics[channel.topic] = {
                "schema": schema.name if schema else None,
                "schema_encoding": schema.encoding if schema else None,
                "message_encoding": channel.message_encoding,
                "machine": machine_of(channel.topic),
                "messages": 0,
                "samples": 0,
                "first_t_ns": None,
                "last_t_ns": None,
                "first_seq": None,
                "last_seq": None,
            }
            if schema is None:
                problems.add(f"{channel.topic}: channel has no schema")
            elif schema.encoding != "protobuf":
                problems.add(f"{channel.topic}: schema encoding {schema.encoding!r}, not 'protobuf'")
            if channel.message_encoding != "protobuf":
                problems.add(
                    f"{channel.topic}: message encoding {channel.message_encoding!r}, not 'protobuf'"
                )
            if t["machine"] is None:
                problems.add(f"{channel.topic}: topic is not <prefix>/<machine>/<group>/<stream>")
            return t

        def message_class(schema, topic):
            if schema.id in classes:
                return classes[schema.id]
            cls = None
            try:
                pool, _ = build_pool(schema.data)
                desc = pool.FindMessageTypeByName(schema.name)
                cls = message_factory.GetMessageClass(desc)
            except Exception as e:  # noqa: BLE001 - report any descriptor problem
                problems.add(f"{topic}: schema {schema.name!r}: cannot build message class: {e}")
            classes[schema.id] = cls
            return cls

        # Channels known from the summary appear even when they carry no message.
        if summary is not None:
            for ch in summary.channels.values():
                topic_entry(summary.schemas.get(ch.schema_id), ch)

        # File order: seq must be consecutive in the order the writer wrote the batches.
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            topic = channel.topic
            t = topic_entry(schema, channel)
            t["messages"] += 1
            if schema is None or schema.encoding != "protobuf":
                continue
            if schema.name.startswith(FOXGLOVE_SCHEMAS):
                # Foxglove's channels beside ours: counted here, read by foxglove_bag.py.
                continue
            cls = message_class(schema, topic)
            if cls is None:
                continue
            msg = cls()
            try:
                msg.ParseFromString(message.data)
            except Exception as e:  # noqa: BLE001
                problems.add(f"{topic}: message #{t['messages']} does not decode as {schema.name}: {e}")
                continue
            field = next((n for n in BATCH_FIELDS if n in cls.DESCRIPTOR.fields_by_name), None)
            samples = list(getattr(msg, field)) if field else [msg]
            cfield = cls.DESCRIPTOR.fields_by_name.get("columns")
            if cfield is not None and field:
                where = f"{topic}: message #{t['messages']}"
                sample_desc = cls.DESCRIPTOR.fields_by_name[field].message_type
                # One columns message (raw batches, v1.3) or a sequence of blocks (points, v1.4).
                if cfield.is_repeated:
                    blocks = list(msg.columns)
                else:
                    blocks = [msg.columns] if msg.HasField("columns") else []
                if blocks and samples:
                    problems.add(f"{where} has both {field} and columns")
                for block in blocks:
                    samples += column_samples(block, sample_desc, where, problems)
            if field and not samples:
                problems.add(f"{topic}: message #{t['messages']} is an empty batch")
            st = streams.setdefault(topic, {"seq": None})
            for s in samples:
                t["samples"] += 1
                mid = getattr(s, "machine_id", None)
                if mid != t["machine"]:
                    problems.add(
                        f"{topic}: sample {t['samples']} has machine_id {mid!r}, topic says {t['machine']!r}"
                    )
                seq = getattr(s, "seq", None)
                if seq is None:
                    problems.add(f"{topic}: {schema.name} samples have no seq")
                else:
                    if st["seq"] is not None and seq != st["seq"] + 1:
                        problems.add(
                            f"{topic}: seq jumps from {st['seq']} to {seq} at sample {t['samples']}"
                        )
                    st["seq"] = seq
                    if t["first_seq"] is None:
                        t["first_seq"] = seq
                    t["last_seq"] = seq
                t_ns = getattr(s, "t_ns", None)
                if t["first_t_ns"] is None:
                    t["first_t_ns"] = t_ns
                t["last_t_ns"] = t_ns

        metadata = {}
        for md in reader.iter_metadata():
            metadata.setdefault(md.name, []).append(dict(md.metadata))

    # Cross-checks against what the writer recorded about itself.
    if summary is not None and summary.statistics is not None:
        counts = summary.statistics.channel_message_counts
        for cid, ch in summary.channels.items():
            n = counts.get(cid, 0)
            got = topics[ch.topic]["messages"]
            if n != got:
                problems.add(f"{ch.topic}: statistics say {n} messages, read {got}")
        total = sum(t["messages"] for t in topics.values())
        if summary.statistics.message_count != total:
            problems.add(
                f"statistics say {summary.statistics.message_count} messages in all, read {total}"
            )
    for rec in metadata.get("scancorr.sample_counts", []):
        for topic, n in rec.items():
            got = topics.get(topic, {}).get("samples")
            if str(got) != n:
                problems.add(f"{topic}: scancorr.sample_counts says {n} samples, read {got}")

    return {
        "file": path,
        "profile": header.profile,
        "library": header.library,
        "topics": topics,
        "metadata": metadata,
    }


def main(argv):
    if len(argv) != 2 or argv[1] in ("-h", "--help"):
        print(__doc__, file=sys.stderr)
        return 2
    problems = Problems()
    try:
        out = read(argv[1], problems)
    except Exception as e:  # noqa: BLE001 - unreadable bag
        print(f"read_bag.py: {argv[1]}: cannot read: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    if not out["topics"]:
        problems.add("bag has no channels")
    json.dump(out, sys.stdout, indent=1, sort_keys=True)
    sys.stdout.write("\n")
    if problems.items:
        n = len(problems.items)
        print(f"read_bag.py: {argv[1]}: {n} problem(s):", file=sys.stderr)
        for p in problems.items[:MAX_PROBLEMS_SHOWN]:
            print(f"  {p}", file=sys.stderr)
        if n > MAX_PROBLEMS_SHOWN:
            print(f"  ... and {n - MAX_PROBLEMS_SHOWN} more", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
