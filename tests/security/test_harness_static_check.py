"""The static check refuses the module-attribute escapes of issue #21 (item 1, first line).

``typing.sys.modules['os']`` passed the publish checks and ran ``id`` as root in the env worker;
``dataclasses.sys``, ``collections._sys``, ``numpy.core`` and runtime-built format strings were
also reachable. Each is now refused before any import, with a reason.
"""

from __future__ import annotations

import pytest

from services.harness.package.errors import PackageRejected
from services.harness.package.safety import check_source

ESCAPES = {
    "typing.sys": "import typing\nOS = typing.sys.modules['os']\n",
    "dataclasses.sys": "import dataclasses\nS = dataclasses.sys\n",
    "dataclasses.inspect": "import dataclasses\nI = dataclasses.inspect\n",
    "collections._sys": "import collections\nS = collections._sys\n",
    "numpy.core": "import numpy as np\nC = np.core\n",
    "numpy._core": "import numpy as np\nC = np._core\n",
    "typing.operator": "import typing\nG = typing.operator.attrgetter\n",
    "runtime format": "def leak(f):\n    return ('{0.' + '_' * 2 + 'globals' + '_' * 2 + '}').format(f)\n",
    "format_map": "def leak(f, t):\n    return t.format_map({'f': f})\n",
    "frame walk": "def leak():\n    g = (x for x in [1])\n    return g.gi_frame.f_back.f_globals\n",
    "private chain": "import typing\nC = typing.collections._sys\n",
}


@pytest.mark.parametrize("source", list(ESCAPES.values()), ids=list(ESCAPES))
def test_escape_is_refused(source: str) -> None:
    with pytest.raises(PackageRejected) as err:
        check_source("tools/probe.py", source)
    assert "not allowed" in str(err.value) or "only allowed" in str(err.value)


def test_ordinary_critic_code_passes() -> None:
    """What critics do stays allowed: numpy, dataclasses, f-strings, private state on self."""
    check_source("tools/ok.py", (
        "import numpy as np\nfrom dataclasses import dataclass\n\n"
        "@dataclass\nclass C:\n    _count: int = 0\n\n"
        "    def step(self, window):\n        self._count += 1\n"
        "        v = np.asarray(window).copy()\n        return f'{self._count} {np.linalg.norm(v):.3f}'\n"
    ))


def test_platform_limits_bound_what_a_package_asks(monkeypatch: pytest.MonkeyPatch) -> None:
    """SKILL.md's critic_hard_limit_ms = 1e9 used to be honoured; the platform's limit wins now,
    and a package asking for less keeps its own."""
    from services.harness.runtime.engine import HarnessRuntime
    from tests.unit.test_harness_runtime import package

    greedy = HarnessRuntime(package({"runtime": {"critic_budget_ms": 1e9, "critic_hard_limit_ms": 1e9}}))
    assert greedy.budget_s == 0.05 and greedy.hard_limit_s == 1.0
    modest = HarnessRuntime(package({"runtime": {"critic_budget_ms": 1.0, "critic_hard_limit_ms": 10.0}}))
    assert modest.budget_s == 0.001 and modest.hard_limit_s == 0.01
    monkeypatch.setenv("ZETTA_CRITIC_MAX_BUDGET_MS", "2")
    monkeypatch.setenv("ZETTA_CRITIC_MAX_HARD_LIMIT_MS", "5")
    assert HarnessRuntime(package({"runtime": {"critic_budget_ms": 1.0}})).hard_limit_s == 0.005
