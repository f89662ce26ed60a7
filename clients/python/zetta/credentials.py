"""How the SDK reaches a gateway that wants TLS and a token.

``Gateway(address, token=..., tls_ca=...)``: the token goes with every call as
``authorization: Bearer <token>`` (unary and streaming calls alike); ``tls_ca`` is the PEM file
(or bytes) of the CA that signed the gateway's certificate, and switches the channel to TLS.
``client_cert``/``client_key`` add a client certificate where the server asks for one.
"""

from __future__ import annotations

from collections.abc import Sequence
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
