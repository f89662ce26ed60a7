"""The error contract in trailing metadata (clients/python/zetta_wire/errors.py): what a service
writes is what a client reads, whatever else the metadata carries."""

from __future__ import annotations

import grpc

from services.common.grpc_errors import ServiceError
from zetta_wire.errors import ErrorDetails, error_metadata, parse_error_metadata


def test_round_trip_of_sessions_and_retry_hint() -> None:
    md = error_metadata(["s1", "s2"], 250)
    assert md == (("zetta-failed-sessions", "s1,s2"), ("retry-after-ms", "250"))
    assert parse_error_metadata([("other", "x"), *md]) == ErrorDetails(["s1", "s2"], 250)


def test_empty_parts_are_omitted_and_read_back_as_none() -> None:
    assert error_metadata() == ()
    assert parse_error_metadata(None) == ErrorDetails([], None)
    assert parse_error_metadata([("zetta-failed-sessions", b"a,,b")]) == ErrorDetails(["a", "b"], None)


def test_service_error_writes_the_contract() -> None:
    err = ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED, "busy", ["s9"], retry_after_ms=40)
    assert parse_error_metadata(err.trailing_metadata()) == ErrorDetails(["s9"], 40)
