"""The SDK installs and imports on its own (clients/python/pyproject.toml): nothing of the services,
only grpcio, protobuf and numpy (gymnasium for the gym envs)."""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CLIENT = ROOT / "clients" / "python"
#: Third-party top-level modules the SDK may import (``zetta.gym`` adds gymnasium, an extra).
ALLOWED = {"grpc", "google", "numpy", "gymnasium"}
#: What the client's install needs in site-packages: grpcio, protobuf and numpy, and what they
#: require themselves (grpcio: typing_extensions).
RUNTIME = ("grpc", "google/protobuf", "google/_upb", "numpy", "numpy.libs", "typing_extensions.py")


def _top_level_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_the_sdk_imports_only_itself_the_stdlib_and_its_dependencies() -> None:
    own = {"zetta", "zetta_wire"}
    for pkg in own:
        for path in sorted((CLIENT / pkg).rglob("*.py")):
            foreign = _top_level_imports(path) - own - ALLOWED - set(sys.stdlib_module_names) - {"__future__"}
            assert not foreign, f"{path.relative_to(ROOT)} imports {sorted(foreign)}"


def _site_packages(module: str) -> Path:
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin is not None
    return Path(spec.origin).parents[len(module.split("."))]


def test_pip_install_of_the_client_alone_imports_and_runs(tmp_path: Path) -> None:
    """Installed with --no-deps into an empty folder, then imported by an interpreter that sees
    only that folder, the standard library and the three runtime dependencies (with their own)."""
    assert (CLIENT / "zetta_wire" / "v1" / "gateway_pb2.py").exists(), "run scripts/gen_proto.py first"
    target = tmp_path / "client"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(CLIENT)], check=True, capture_output=True)
    deps = tmp_path / "deps"
    site = _site_packages("numpy")
    for rel in RUNTIME:
        if (site / rel).exists():
            (deps / rel).parent.mkdir(parents=True, exist_ok=True)
            (deps / rel).symlink_to(site / rel)
    probe = (
        "import sys\n"
        f"sys.path[:] = [p for p in sys.path if 'site-packages' not in p] + [{str(target)!r}, {str(deps)!r}]\n"
        "import numpy as np, zetta\n"
        "from zetta_wire.codec import decode, encode\n"
        "from zetta_wire.v1 import gateway_pb2\n"
        "assert (decode(encode(np.arange(6, dtype='float32').reshape(2, 3))) == np.arange(6).reshape(2, 3)).all()\n"
        "assert gateway_pb2.ResetRequest(session_ids=['s']).session_ids == ['s']\n"
        "assert zetta.Gateway.__module__ == 'zetta.client' and zetta.__file__.startswith(sys.path[-2])\n"
        "for name in ('services', 'redis', 'torch', 'prometheus_client'):\n"
        "    assert name not in sys.modules, name\n"
        "try:\n"
        "    import services\n"
        "except ImportError:\n"
        "    print('alone')\n"
    )
    out = subprocess.run([sys.executable, "-S", "-s", "-c", probe], cwd=tmp_path, capture_output=True, text=True,
                         env={"PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "alone"
