#!/usr/bin/env python3
"""Generates `scancorr/v1/scancorr_pb2.py` and `scancorr_pb2.pyi` from proto/ with the protoc
that `grpcio-tools` bundles (pinned in tests/python/requirements.txt).

    python gen_proto.py            # writes them into scancorr/v1/
    python gen_proto.py --check    # exits 1 (and says which) when they are not current
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import tempfile

HERE = pathlib.Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent.parent / "proto"
PROTO = "scancorr/v1/scancorr.proto"
OUT = HERE / "scancorr"
FILES = ["v1/scancorr_pb2.py", "v1/scancorr_pb2.pyi"]


def generate(out: pathlib.Path) -> None:
    from grpc_tools import protoc

    rc = protoc.main(
        ["protoc", f"-I{PROTO_ROOT}", f"--python_out={out}", f"--pyi_out={out}", str(PROTO_ROOT / PROTO)]
    )
    if rc != 0:
        raise SystemExit(f"protoc failed ({rc}) on {PROTO_ROOT / PROTO}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="compare instead of writing")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        generate(pathlib.Path(tmp))
        stale = []
        for f in FILES:
            new = (pathlib.Path(tmp) / "scancorr" / f).read_bytes()
            dst = OUT / f
            if a.check:
                if not dst.is_file() or dst.read_bytes() != new:
                    stale.append(str(dst.relative_to(HERE)))
            else:
                dst.write_bytes(new)
        if stale:
            print(
                f"not current with {PROTO}: {', '.join(stale)} — run `python clients/python/gen_proto.py`",
                file=sys.stderr,
            )
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
