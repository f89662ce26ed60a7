"""Who is calling the gateway: bearer tokens mapped to identities and roles.

With ZETTA_AUTH_TOKENS_FILE set, every GatewayService call must carry ``authorization: Bearer
<token>`` of a ``user`` or ``admin`` identity, and every WorkerRegistryService call a ``worker``
token. Sessions belong to the identity that created them; only it or an ``admin`` may use, close
or list them. The file holds SHA-256 digests, never the tokens themselves, one identity a line:

    # identity  role    sha256 of the token
    alice       user    3f1c...
    ops         admin   9a7e...
    env-pool    worker  c41b...

``python -m services.gateway.auth NAME ROLE`` makes a token and prints it with its line. Without
the file, auth is off: every caller is an anonymous admin (the embedded loopback default).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import sys
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

import grpc

from services.common import grpc_errors as ge
from services.common.config import ConfigError

ROLES = ("user", "admin", "worker")


@dataclass(frozen=True)
class Identity:
    """An authenticated caller."""

    name: str
    role: str

    def owns(self, owner: str) -> bool:
        """May this caller use a session created by ``owner``?"""
        return self.role == "admin" or owner == self.name


#: Auth off: everybody may do everything; sessions are created with owner "".
ANONYMOUS = Identity("", "admin")
#: The caller of the gateway call running in this task.
CALLER: ContextVar[Identity] = ContextVar("zetta_caller", default=ANONYMOUS)


def digest(token: str) -> str:
    """The SHA-256 hex digest the tokens file stores."""
    return hashlib.sha256(token.encode()).hexdigest()


def read_tokens_file(path: str) -> dict[str, Identity]:
    """digest -> identity; ConfigError naming the file and line for anything malformed."""
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ConfigError(f"gateway: ZETTA_AUTH_TOKENS_FILE={path!r} cannot be read: {exc.strerror}") from None
    table: dict[str, Identity] = {}
    for n, line in enumerate(text.splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) != 3 or fields[1] not in ROLES or len(fields[2]) != 64:
            raise ConfigError(f"gateway: {path}:{n}: expected 'IDENTITY ROLE SHA256' with ROLE one of "
                              f"{', '.join(ROLES)} and a 64-hex-digit digest")
        table[fields[2].lower()] = Identity(fields[0], fields[1])
    if not table:
        raise ConfigError(f"gateway: ZETTA_AUTH_TOKENS_FILE={path!r} names no identity")
    return table


class Authenticator:
    """Maps a call's bearer token to an identity and checks its role."""

    def __init__(self, table: dict[str, Identity] | None = None) -> None:
        self._table = table

    @property
    def enabled(self) -> bool:
        """False: every caller is ANONYMOUS."""
        return self._table is not None

    def identify(self, context: grpc.aio.ServicerContext) -> Identity:
        """The caller, or UNAUTHENTICATED."""
        if self._table is None:
            return ANONYMOUS
        header = next((v for k, v in context.invocation_metadata() or () if k == "authorization"), "")
        if not isinstance(header, str) or not header.startswith("Bearer "):
            raise ge.unauthenticated("this gateway requires a token: send the metadata 'authorization: Bearer "
                                     "<token>' (zetta.Gateway(address, token=...)); ask its operator for one")
        wanted = digest(header[len("Bearer "):].strip())
        for known, who in self._table.items():
            if hmac.compare_digest(known, wanted):
                return who
        raise ge.unauthenticated("the token is not recognised by this gateway (revoked, or from another deployment)")

    def client(self, context: grpc.aio.ServicerContext) -> Identity:
        """A user or admin calling GatewayService; sets CALLER for the rest of the call."""
        who = self.identify(context)
        if who.role == "worker":
            raise ge.permission_denied(f"identity {who.name!r} is a worker credential; it may only register "
                                       "and heartbeat (WorkerRegistryService)")
        CALLER.set(who)
        return who

    def worker(self, context: grpc.aio.ServicerContext) -> Identity:
        """An env worker calling WorkerRegistryService."""
        who = self.identify(context)
        if who.role not in ("worker", "admin"):
            raise ge.permission_denied(f"identity {who.name!r} ({who.role}) may not register or heartbeat workers; "
                                       "that needs a worker credential (ZETTA_WORKER_TOKEN on the env worker)")
        return who


def main(argv: list[str]) -> int:
    """``python -m services.gateway.auth NAME ROLE``: a new token and its tokens-file line."""
    if len(argv) != 2 or argv[1] not in ROLES:
        print(f"usage: python -m services.gateway.auth NAME {{{','.join(ROLES)}}}", file=sys.stderr)
        return 2
    token = secrets.token_urlsafe(32)
    print(f"token (give it to {argv[0]}; it is not stored): {token}")
    print(f"line for ZETTA_AUTH_TOKENS_FILE: {argv[0]} {argv[1]} {digest(token)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
