"""Protobuf message classes for the scancorr wire contract, built at run time.

scancorr does not ship generated Python code: every bag it writes carries the serialized
`google.protobuf.FileDescriptorSet` of `proto/scancorr/v1/scancorr.proto` as the schema data
of its channels, and that is all a consumer needs.

    fds = load_descriptor_set("r.mcap")        # or a .bin holding a serialized FileDescriptorSet
    classes = message_classes(fds)             # {"scancorr.v1.CorrectedPointBatch": <class>, ...}
    batch = classes["scancorr.v1.CorrectedPointBatch"].FromString(payload)
    message_to_dict(batch)                     # {"points": [{"seq": 0, "surface": {...}, ...}]}
"""

from google.protobuf import descriptor as _descriptor
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

MCAP_MAGIC = b"\x89MCAP"
# The package whose descriptor set a bag is searched for.
PACKAGE = "scancorr.v1"


def load_descriptor_set(path):
    """The serialized FileDescriptorSet (bytes) from `path`.

    `path` is either an MCAP bag written by scancorr (the schema data of its first protobuf
    schema of package `scancorr.v1`; needs the `mcap` package) or a file holding a serialized
    FileDescriptorSet (e.g. `scancorr_v1_descriptor.bin`). Raises ValueError if there is none.
    """
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
        if head != MCAP_MAGIC:
            data = head + f.read()
            _parse(data, path)  # fail early on a file that is not a descriptor set
            return data
        f.seek(0)
        from mcap.records import Schema  # imported here: only bags need `mcap`
        from mcap.stream_reader import StreamReader

        for record in StreamReader(f).records:
            if (
                isinstance(record, Schema)
                and record.encoding == "protobuf"
                and record.name.startswith(PACKAGE + ".")
            ):
                return bytes(record.data)
    raise ValueError(f"{path}: the bag has no protobuf schema of package {PACKAGE}")


def _parse(data, origin="descriptor set"):
    fds = descriptor_pb2.FileDescriptorSet()
    try:
        fds.ParseFromString(data)
    except Exception as e:  # noqa: BLE001 - any parse failure means "not a descriptor set"
        raise ValueError(f"{origin}: not a serialized FileDescriptorSet: {e}") from e
    if not fds.file:
        raise ValueError(f"{origin}: the FileDescriptorSet holds no file")
    return fds


def build_pool(fds_bytes):
    """A fresh DescriptorPool holding every file of a serialized FileDescriptorSet
    (dependencies added before the files that import them)."""
    fds = _parse(fds_bytes)
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
            raise ValueError(f"the descriptor set lacks the imported file {name}")
        for dep in f.dependency:
            add(dep, stack + (name,))
        pool.Add(f)
        added.add(name)

    for name in files:
        add(name)
    return pool


def message_classes(fds_bytes):
    """{full message name: message class} for every message (nested ones too) of the set."""
    pool = build_pool(fds_bytes)
    fds = _parse(fds_bytes)
    out = {}

    def walk(desc):
        out[desc.full_name] = message_factory.GetMessageClass(desc)
        for nested in desc.nested_types:
            walk(nested)

    for f in fds.file:
        for desc in pool.FindFileByName(f.name).message_types_by_name.values():
            walk(desc)
    return out


_MESSAGE = _descriptor.FieldDescriptor.TYPE_MESSAGE


def message_to_dict(msg):
    """A decoded message as plain Python values: every field (defaults included) under its
    `.proto` name; nested messages as dicts, repeated fields as lists, 64-bit integers as
    `int` (unlike `json_format`, which turns them into strings), enums as their number."""
    out = {}
    for field in msg.DESCRIPTOR.fields:
        value = getattr(msg, field.name)
        if field.type == _MESSAGE:
            if _is_repeated(field):
                if field.message_type.GetOptions().map_entry:
                    value = {k: _plain(v) for k, v in value.items()}
                else:
                    value = [message_to_dict(v) for v in value]
            elif msg.HasField(field.name):
                value = message_to_dict(value)
            else:
                value = None
        elif _is_repeated(field):
            value = list(value)
        out[field.name] = value
    return out


def _plain(v):
    return message_to_dict(v) if hasattr(v, "DESCRIPTOR") else v


def _is_repeated(field):
    # `is_repeated` is the newer spelling; `label` is deprecated in recent protobuf releases.
    rep = getattr(field, "is_repeated", None)
    if rep is not None:
        return rep() if callable(rep) else bool(rep)
    return field.label == _descriptor.FieldDescriptor.LABEL_REPEATED
