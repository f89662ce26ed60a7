"""Builds the Python stubs from proto/ (the one source of the API) into clients/python/zetta/v1.

The stubs are build output: they are never edited by hand and are not committed. Every other
language generates its own from the same files (see docs/other-languages.md).
"""

from __future__ import annotations

import sys
from importlib import resources
from pathlib import Path

from grpc_tools import protoc

ROOT = Path(__file__).resolve().parent.parent
PROTO_ROOT = ROOT / "proto"
OUT_ROOT = ROOT / "clients" / "python"


def main() -> int:
    protos = sorted(str(p.relative_to(PROTO_ROOT)) for p in (PROTO_ROOT / "zetta" / "v1").glob("*.proto"))
    if not protos:
        print(f"no .proto files under {PROTO_ROOT}", file=sys.stderr)
        return 1
    well_known = str(resources.files("grpc_tools") / "_proto")
    code = protoc.main(
        [
            "grpc_tools.protoc",
            f"-I{PROTO_ROOT}",
            f"-I{well_known}",
            f"--python_out={OUT_ROOT}",
            f"--pyi_out={OUT_ROOT}",
            f"--grpc_python_out={OUT_ROOT}",
            *protos,
        ]
    )
    if code != 0:
        print(f"protoc failed with exit code {code}", file=sys.stderr)
        return code
    (OUT_ROOT / "zetta" / "v1" / "__init__.py").write_text('"""Generated from proto/zetta/v1 by scripts/gen_proto.py."""\n')
    print(f"generated stubs for {len(protos)} files into {OUT_ROOT / 'zetta' / 'v1'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
