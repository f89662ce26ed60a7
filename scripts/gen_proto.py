"""Builds the Python stubs from proto/ (the one source of the API) into clients/python/zetta_wire/v1.

The stubs are build output: they are never edited by hand and are not committed. Every other
language generates its own from the same files (see docs/other-languages.md). protoc names the
Python modules after the proto paths (``zetta.v1``); the stubs live in the ``zetta_wire`` package
that the SDK and the services share, so their imports of each other are rewritten to it.
"""

from __future__ import annotations

import re
import sys
import tempfile
from importlib import resources
from pathlib import Path

from grpc_tools import protoc

ROOT = Path(__file__).resolve().parent.parent
PROTO_ROOT = ROOT / "proto"
OUT = ROOT / "clients" / "python" / "zetta_wire" / "v1"
#: ``from zetta.v1 import x_pb2`` (protoc's import of a sibling file) -> ``from zetta_wire.v1 import``.
_SIBLING_IMPORT = re.compile(r"^from zetta\.v1 import ", re.MULTILINE)


def main() -> int:
    protos = sorted(str(p.relative_to(PROTO_ROOT)) for p in (PROTO_ROOT / "zetta" / "v1").glob("*.proto"))
    if not protos:
        print(f"no .proto files under {PROTO_ROOT}", file=sys.stderr)
        return 1
    well_known = str(resources.files("grpc_tools") / "_proto")
    with tempfile.TemporaryDirectory() as tmp:
        code = protoc.main(
            [
                "grpc_tools.protoc",
                f"-I{PROTO_ROOT}",
                f"-I{well_known}",
                f"--python_out={tmp}",
                f"--pyi_out={tmp}",
                f"--grpc_python_out={tmp}",
                *protos,
            ]
        )
        if code != 0:
            print(f"protoc failed with exit code {code}", file=sys.stderr)
            return code
        OUT.mkdir(parents=True, exist_ok=True)
        for generated in sorted((Path(tmp) / "zetta" / "v1").iterdir()):
            text = _SIBLING_IMPORT.sub("from zetta_wire.v1 import ", generated.read_text())
            (OUT / generated.name).write_text(text)
    (OUT / "__init__.py").write_text('"""Generated from proto/zetta/v1 by scripts/gen_proto.py."""\n')
    print(f"generated stubs for {len(protos)} files into {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
