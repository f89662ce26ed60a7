"""The API tests share one stack (2 env workers x 4 slots, 200 ms / 1000 ms heartbeats).

The stack itself and the ``gw`` client fixture live in tests/conftest.py so that the fault tests
that leave the stack healthy (validation, leases, admission) reuse the same processes.
"""

from __future__ import annotations

import pytest

from services.ops.local_stack import LocalStack


@pytest.fixture(scope="session")
def stack(shared_stack: LocalStack) -> LocalStack:
    """The session-wide stack, started once for all API tests."""
    return shared_stack
