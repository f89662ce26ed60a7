"""How the SDK reaches a gateway that wants TLS and a token.

``Gateway(address, token=..., tls_ca=...)``: the token goes with every call as
``authorization: Bearer <token>`` (unary and streaming calls alike); ``tls_ca`` is the PEM file
(or bytes) of the CA that signed the gateway's certificate, and switches the channel to TLS.
``client_cert``/``client_key`` add a client certificate where the server asks for one.

:class:`ClientCredentials` holds the same settings for every channel a client opens (the gateway,
the critic service's harness registry) and reads them from the environment
(``ClientCredentials.from_env()``: ZETTA_TOKEN, ZETTA_TLS_CA, ZETTA_TLS_CERT, ZETTA_TLS_KEY); the
``zetta`` command line takes them as flags too (:func:`add_credential_flags`).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc


def _pem(value: str | bytes | Path | None) -> bytes | None:
    if value is None or isinstance(value, bytes):
        return value
    return Path(value).read_bytes()


def _with_token(details: grpc.aio.ClientCallDetails, token: str) -> grpc.aio.ClientCallDetails:
    metadata = grpc.aio.Metadata()
    for key, value in details.metadata or ():  # (key, value) pairs, as a tuple or as grpc.aio.Metadata
        metadata.add(key, value)
    metadata.add("authorization", f"Bearer {token}")
    return grpc.aio.ClientCallDetails(details.method, details.timeout, metadata, details.credentials,
                                      details.wait_for_ready)


class _UnaryBearer(grpc.aio.UnaryUnaryClientInterceptor):
    """Adds the bearer token to every unary call (grpc.aio files an interceptor under one kind only)."""

    def __init__(self, token: str) -> None:
        self._token = token

    async def intercept_unary_unary(self, continuation, details, request):  # type: ignore[no-untyped-def]
        return await continuation(_with_token(details, self._token), request)


class _StreamBearer(grpc.aio.StreamStreamClientInterceptor):
    """Adds the bearer token to every bidirectional stream (StepStream)."""

    def __init__(self, token: str) -> None:
        self._token = token

    async def intercept_stream_stream(self, continuation, details, request_iterator):  # type: ignore[no-untyped-def]
        return await continuation(_with_token(details, self._token), request_iterator)


def gateway_channel(address: str, options: Sequence[tuple[str, Any]], token: str | None = None,
                    tls_ca: str | bytes | Path | None = None, client_cert: str | bytes | Path | None = None,
                    client_key: str | bytes | Path | None = None) -> grpc.aio.Channel:
    """A channel to the gateway: TLS when ``tls_ca`` is given, the token on every call when given."""
    interceptors: list[grpc.aio.ClientInterceptor] | None = [_UnaryBearer(token), _StreamBearer(token)] if token else None
    if tls_ca is None:
        return grpc.aio.insecure_channel(address, options=list(options), interceptors=interceptors)
    creds = grpc.ssl_channel_credentials(root_certificates=_pem(tls_ca), private_key=_pem(client_key),
                                         certificate_chain=_pem(client_cert))
    return grpc.aio.secure_channel(address, creds, options=list(options), interceptors=interceptors)


#: Environment variables of a client's credentials, shared by ``ClientCredentials.from_env``, the
#: ``zetta`` command line and the services (which read the same TLS variables for their own
#: certificate): the bearer token (or a file holding it) and the PEM files of the CA, the client
#: certificate and its key.
TOKEN_VAR = "ZETTA_TOKEN"
TOKEN_FILE_VAR = "ZETTA_TOKEN_FILE"
CA_VAR = "ZETTA_TLS_CA"
CERT_VAR = "ZETTA_TLS_CERT"
KEY_VAR = "ZETTA_TLS_KEY"


@dataclass(frozen=True)
class ClientCredentials:
    """What a client presents: a token for the gateway, the CA that signed the servers'
    certificates (TLS on when set), and a client certificate for servers that require one (every
    service but the gateway: the critic service, the env and policy workers)."""

    token: str | None = None
    tls_ca: str | None = None
    client_cert: str | None = None
    client_key: str | None = None

    def __post_init__(self) -> None:
        if bool(self.client_cert) != bool(self.client_key):
            raise ValueError(f"a client certificate needs its key: give both {CERT_VAR} and {KEY_VAR} "
                             "(--tls-cert and --tls-key) or neither")
        if self.client_cert and not self.tls_ca:
            raise ValueError(f"a client certificate needs TLS: give the CA too ({CA_VAR}, --tls-ca)")

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, token: str | None = None,
                 token_file: str | None = None, tls_ca: str | None = None, client_cert: str | None = None,
                 client_key: str | None = None) -> "ClientCredentials":
        """From ZETTA_TOKEN (or ZETTA_TOKEN_FILE), ZETTA_TLS_CA, ZETTA_TLS_CERT and ZETTA_TLS_KEY;
        arguments that are not None win over the variables."""
        env = os.environ if environ is None else environ
        token_file = token_file or (None if token else env.get(TOKEN_FILE_VAR) or None)
        if token is None and token_file:
            token = Path(token_file).read_text().strip()
        return cls(
            token=token if token is not None else env.get(TOKEN_VAR) or None,
            tls_ca=tls_ca if tls_ca is not None else env.get(CA_VAR) or None,
            client_cert=client_cert if client_cert is not None else env.get(CERT_VAR) or None,
            client_key=client_key if client_key is not None else env.get(KEY_VAR) or None,
        )

    @property
    def tls(self) -> bool:
        """Whether channels speak TLS."""
        return self.tls_ca is not None

    def gateway_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :class:`zetta.Gateway` (and ``SyncGateway``)."""
        return {"token": self.token, "tls_ca": self.tls_ca, "client_cert": self.client_cert,
                "client_key": self.client_key}

    def channel_credentials(self) -> grpc.ChannelCredentials | None:
        """TLS credentials (verify the server against the CA, present the client certificate when
        given); None without TLS."""
        if self.tls_ca is None:
            return None
        return grpc.ssl_channel_credentials(root_certificates=_pem(self.tls_ca), private_key=_pem(self.client_key),
                                            certificate_chain=_pem(self.client_cert))

    def sync_channel(self, address: str, options: Sequence[tuple[str, Any]] = ()) -> grpc.Channel:
        """A blocking channel to a service other than the gateway (no token: they authenticate
        clients by certificate)."""
        creds = self.channel_credentials()
        if creds is None:
            return grpc.insecure_channel(address, options=list(options))
        return grpc.secure_channel(address, creds, options=list(options))

    def aio_channel(self, address: str, options: Sequence[tuple[str, Any]] = ()) -> grpc.aio.Channel:
        """An asyncio channel to a service other than the gateway."""
        creds = self.channel_credentials()
        if creds is None:
            return grpc.aio.insecure_channel(address, options=list(options))
        return grpc.aio.secure_channel(address, creds, options=list(options))


def add_credential_flags(parser: argparse.ArgumentParser) -> None:
    """``--token-file``, ``--tls-ca``, ``--tls-cert``, ``--tls-key`` (each defaults to its variable)."""
    group = parser.add_argument_group(
        "credentials", f"how to reach a stack with auth or TLS on (docs/security.md); each defaults to its variable: "
                       f"{TOKEN_VAR} or {TOKEN_FILE_VAR}, {CA_VAR}, {CERT_VAR}, {KEY_VAR}")
    group.add_argument("--token-file", help=f"file holding the gateway token (or set {TOKEN_VAR})")
    group.add_argument("--tls-ca", help="PEM file of the CA that signed the servers' certificates (turns TLS on)")
    group.add_argument("--tls-cert", help="PEM file of this client's certificate (services other than the gateway "
                                          "require one)")
    group.add_argument("--tls-key", help="PEM file of the client certificate's key")


def credentials_from_args(args: argparse.Namespace) -> ClientCredentials:
    """The credentials of parsed arguments (see :func:`add_credential_flags`), the variables filling in."""
    return ClientCredentials.from_env(token_file=args.token_file, tls_ca=args.tls_ca, client_cert=args.tls_cert,
                                      client_key=args.tls_key)
