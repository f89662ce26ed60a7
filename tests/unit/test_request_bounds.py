"""The gateway's request bounds and the bounded error metadata, without a server."""

from __future__ import annotations

import grpc
import pytest

from services.common.grpc_errors import MAX_FAILED_IDS, MAX_MESSAGE_CHARS, ServiceError
from services.gateway.bounds import check_session_ids, name_ids


def test_name_ids_counts_the_rest() -> None:
    assert name_ids(["a", "b"]) == "a, b"
    assert name_ids([str(i) for i in range(10)], shown=3) == "0, 1, 2 and 7 more"


@pytest.mark.parametrize("sids,needle", [
    ([], "empty"),
    (["a"] * 5, "at most 4"),
    (["ok", "\u00e9"], "session_ids[1]"),
    (["x" * 65], "session_ids[0]"),
    (["a", "b", "a"], "more than once in one call: a"),
])
def test_bad_id_lists_are_invalid(sids: list[str], needle: str) -> None:
    with pytest.raises(ServiceError) as err:
        check_session_ids(sids, limit=4)
    assert err.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert needle in err.value.message


def test_good_ids_pass() -> None:
    check_session_ids(["0123456789abcdef0123456789abcdef", "a-b_c.d"], limit=4)


def test_failed_ids_in_metadata_are_bounded() -> None:
    ids = [f"{i:032x}" for i in range(5000)] + ["\u00e9t\u00e9"]
    md = dict(ServiceError(grpc.StatusCode.NOT_FOUND, "x", ids).trailing_metadata())
    listed = md["zetta-failed-sessions"].split(",")
    assert len(listed) == MAX_FAILED_IDS
    assert int(md["zetta-failed-sessions-more"]) == len(ids) - MAX_FAILED_IDS
    assert all(v.isascii() for v in md.values())


def test_long_messages_are_cut() -> None:
    err = ServiceError(grpc.StatusCode.NOT_FOUND, "y" * 100_000)
    assert len(err.message) <= MAX_MESSAGE_CHARS and "cut from 100000 characters" in err.message
