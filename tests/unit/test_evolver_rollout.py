"""Which failed calls make an attempt infrastructure-invalid (rerun) and which are errors to report."""

from __future__ import annotations

import grpc

from services.evolver.rollout import is_infrastructure
from zetta.client import ZettaError


def test_lost_sessions_and_unreachable_workers_are_infrastructure() -> None:
    """A LOST session, an unreachable worker, a deadline under load: rerun the same key."""
    assert is_infrastructure(ZettaError(grpc.StatusCode.FAILED_PRECONDITION,
                                        "session(s) abc LOST (worker env-0 stopped heartbeating); create new sessions"))
    assert is_infrastructure(ZettaError(grpc.StatusCode.UNAVAILABLE, "env worker env-0 unreachable"))
    assert is_infrastructure(ZettaError(grpc.StatusCode.DEADLINE_EXCEEDED, "policy worker: Deadline Exceeded"))


def test_configuration_errors_are_not_retried() -> None:
    """A missing video directory or critic service is a mistake a rerun would repeat; bad input too."""
    assert not is_infrastructure(ZettaError(grpc.StatusCode.FAILED_PRECONDITION,
                                            "session s asked for a video but this env worker has no ZETTA_VIDEO_DIR"))
    assert not is_infrastructure(ZettaError(grpc.StatusCode.INVALID_ARGUMENT, "unknown task 'x'"))
    assert not is_infrastructure(ZettaError(grpc.StatusCode.NOT_FOUND,
                                            "env worker env-0: harness 'evolved-6@9' from the critic service: no such version"))
    assert is_infrastructure(ZettaError(grpc.StatusCode.NOT_FOUND, "session(s) abc closed (lease expired)"))
