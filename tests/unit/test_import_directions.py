"""The packages import each other only in the allowed directions and without cycles
(tests/import_graph.py holds the table; docs/architecture.md draws it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.import_graph import check_in_fresh_process as check

ROOT = Path(__file__).resolve().parents[2]


def test_the_tree_keeps_the_allowed_directions_and_has_no_cycle() -> None:
    assert check(ROOT) == []


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for pkg in ("services", "services/common", "services/critic", "services/env_worker", "services/gateway",
                "services/policy_worker", "services/ops", "clients/python/zetta", "clients/python/zetta_wire"):
        (tmp_path / pkg).mkdir(parents=True, exist_ok=True)
        (tmp_path / pkg / "__init__.py").touch()
    return tmp_path


@pytest.mark.parametrize(
    ("files", "needle"),
    [
        ({"services/gateway/servicer.py": "from zetta.client import Gateway\n",
          "clients/python/zetta/client.py": ""}, "services.gateway.servicer imports zetta.client"),
        ({"clients/python/zetta/client.py": "def f():\n    from services.common import config\n",
          "services/common/config.py": ""}, "zetta.client imports services.common.config"),
        ({"services/critic/servicer.py": "from services.env_worker import harness_loop\n",
          "services/env_worker/harness_loop.py": ""}, "services.critic.servicer imports services.env_worker.harness_loop"),
        ({"services/env_worker/x.py": "import services.critic.registry\n",
          "services/critic/registry.py": ""}, "services.env_worker.x imports services.critic.registry"),
        ({"services/policy_worker/oracle.py": "from services.env_worker.families.task_state import X\n",
          "services/env_worker/families/__init__.py": "", "services/env_worker/families/task_state.py": ""},
         "services.policy_worker.oracle imports services.env_worker.families.task_state"),
        ({"clients/python/zetta_wire/codec.py": "from zetta import client\n",
          "clients/python/zetta/client.py": ""}, "zetta_wire.codec imports zetta.client"),
        ({"services/ops/a.py": "from services.ops import b\n", "services/ops/b.py": "from . import c\n",
          "services/ops/c.py": "import services.ops.a\n"}, "import cycle: services.ops.a <-> services.ops.b <-> services.ops.c"),
        ({"services/common/a.py": "from services.common import b\n",
          "services/common/b.py": "def f():\n    from services.common import a\n"},
         "import cycle: services.common.a <-> services.common.b"),
        ({"services/common/a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from services.common.b import X\n",
          "services/common/b.py": "from services.common.a import Y\n"}, "import cycle: services.common.a <-> services.common.b"),
    ],
)
def test_a_violating_tree_is_reported(tmp_path: Path, files: dict[str, str], needle: str) -> None:
    problems = check(_tree(tmp_path, files))
    assert any(needle in p for p in problems), problems


def test_allowed_imports_and_deferred_cycles_pass(tmp_path: Path) -> None:
    """The public family API, the SDK from ops, and a shared module two others import."""
    files = {
        "services/policy_worker/data.py": "def f():\n    from services.env_worker.families import get_family\n",
        "services/env_worker/families/__init__.py": "",
        "services/ops/cli.py": "from zetta.client import Gateway\nfrom services.gateway import servicer\n",
        "services/gateway/servicer.py": "from zetta_wire.codec import decode\n",
        "clients/python/zetta/client.py": "from zetta_wire import codec\n",
        "clients/python/zetta_wire/codec.py": "",
        "services/common/a.py": "from services.common import b\n",
        "services/common/c.py": "def f():\n    from services.common import b\n",
        "services/common/b.py": "import math\n",
    }
    assert check(_tree(tmp_path, files)) == []
