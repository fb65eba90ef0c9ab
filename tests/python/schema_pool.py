"""A descriptor pool from a serialized FileDescriptorSet (an MCAP schema record's data, or a
Foxglove WebSocket channel's decoded schema), for the tests' independent decoders."""

from google.protobuf import descriptor_pb2, descriptor_pool


def pool_of(data):
    """The pool holding every file of the FileDescriptorSet `data`, added dependencies first,
    whatever the set's order."""
    files = list(descriptor_pb2.FileDescriptorSet.FromString(data).file)
    pool = descriptor_pool.DescriptorPool()
    while files:
        left = []
        for f in files:
            try:
                pool.Add(f)
            except Exception:  # noqa: BLE001 - a dependency not added yet
                left.append(f)
        if len(left) == len(files):
            raise ValueError(f"unresolvable schema files: {[f.name for f in left]}")
        files = left
    return pool
