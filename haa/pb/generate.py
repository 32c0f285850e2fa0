"""Generate the protobuf and gRPC modules in `haa/pb/` from `proto/haa/pb/*.proto`.

The generated modules are committed so that `pip install` needs no code generation step;
`tests/test_proto_fresh.py` regenerates them into a temporary folder and fails when the committed copies
are stale. Run `make proto` (or `python -m haa.pb.generate`) after editing a `.proto` file.
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PROTO_ROOT = REPO / "proto"


def proto_files() -> list[Path]:
    return sorted((PROTO_ROOT / "haa" / "pb").glob("*.proto"))


def generate(out_dir: Path) -> list[Path]:
    """Run protoc (from grpcio-tools) on every .proto file, writing under `out_dir`; return written files."""
    import grpc_tools
    from grpc_tools import protoc

    include = Path(grpc_tools.__file__).parent / "_proto"
    files = [str(p.relative_to(PROTO_ROOT)) for p in proto_files()]
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"-I{include}",
        f"--python_out={out_dir}",
        f"--pyi_out={out_dir}",
        f"--grpc_python_out={out_dir}",
        *files,
    ]
    rc = protoc.main(args)
    if rc != 0:
        raise RuntimeError(f"protoc failed with exit code {rc}")
    return sorted((out_dir / "haa" / "pb").glob("*_pb2*.py*"))


def main() -> int:
    written = generate(REPO)
    for path in written:
        print(path.relative_to(REPO))
    return 0


if __name__ == "__main__":
    sys.exit(main())
