"""TLS for every server and every service-to-service channel, from ZETTA_TLS_* variables.

Set ZETTA_TLS_CERT, ZETTA_TLS_KEY and ZETTA_TLS_CA together (PEM files; scripts/make_certs.sh
makes a CA and signed certificates): the service then serves TLS only, and every channel it
opens to another service verifies the peer against the CA and presents the same certificate as
its client certificate (mutual TLS). ZETTA_TLS_CLIENT_AUTH says whether this service's server
requires a client certificate: by default every service but the gateway does (the gateway's
clients authenticate with tokens, docs/security.md). Unset, everything is plaintext, which is
only meant for loopback (the embedded default). A partial or unreadable setting stops the
service at start-up (ConfigError).
"""

from __future__ import annotations

import os
import ssl
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import grpc

from services.common.config import ConfigError, EnvReader

_VARS = ("ZETTA_TLS_CERT", "ZETTA_TLS_KEY", "ZETTA_TLS_CA")


@dataclass(frozen=True)
class TLSFiles:
    """The PEM bytes of this process's certificate, its key and the CA it trusts."""

    cert: bytes
    key: bytes
    ca: bytes
    client_auth: bool


def read_tls(environ: Mapping[str, str] | None = None, client_auth_default: bool = True) -> TLSFiles | None:
    """The TLS files named by ZETTA_TLS_*, checked (readable, the key matches the certificate);
    None when none is set; ConfigError naming the variable otherwise."""
    env = os.environ if environ is None else environ
    given = {k: env.get(k, "") for k in _VARS}
    reader = EnvReader(env)
    client_auth = reader.bool("ZETTA_TLS_CLIENT_AUTH", client_auth_default)
    if not any(given.values()):
        reader.finish("tls")
        return None
    missing = [k for k, v in given.items() if not v]
    if missing:
        raise ConfigError(f"tls: set ZETTA_TLS_CERT, ZETTA_TLS_KEY and ZETTA_TLS_CA together; missing: {', '.join(missing)}")
    blobs: dict[str, bytes] = {}
    for name, path in given.items():
        try:
            with open(path, "rb") as fh:
                blobs[name] = fh.read()
        except OSError as exc:
            raise ConfigError(f"tls: {name}={path!r} cannot be read: {exc.strerror}") from None
        if b"-----BEGIN" not in blobs[name]:
            raise ConfigError(f"tls: {name}={path!r} is not a PEM file")
    try:
        ctx = ssl.create_default_context(cadata=blobs["ZETTA_TLS_CA"].decode())
        ctx.load_cert_chain(given["ZETTA_TLS_CERT"], given["ZETTA_TLS_KEY"])
    except (ssl.SSLError, ValueError) as exc:
        raise ConfigError(f"tls: ZETTA_TLS_CERT, ZETTA_TLS_KEY and ZETTA_TLS_CA do not form a valid set: {exc}") from None
    reader.finish("tls")
    return TLSFiles(blobs["ZETTA_TLS_CERT"], blobs["ZETTA_TLS_KEY"], blobs["ZETTA_TLS_CA"], client_auth)


@lru_cache(maxsize=1)
def process_tls() -> TLSFiles | None:
    """This process's TLS settings, read once."""
    return read_tls()


def server_credentials(tls: TLSFiles) -> grpc.ServerCredentials:
    """Credentials for ``add_secure_port``; client certificates required when ``client_auth``."""
    return grpc.ssl_server_credentials([(tls.key, tls.cert)], root_certificates=tls.ca,
                                       require_client_auth=tls.client_auth)


def channel_credentials(tls: TLSFiles) -> grpc.ChannelCredentials:
    """Verify the peer against the CA and present this process's certificate (mutual TLS)."""
    return grpc.ssl_channel_credentials(root_certificates=tls.ca, private_key=tls.key, certificate_chain=tls.cert)


def aio_channel(address: str, options: Sequence[tuple[str, Any]] = ()) -> grpc.aio.Channel:
    """An asyncio channel to another service: TLS when this process has TLS settings."""
    tls = process_tls()
    if tls is None:
        return grpc.aio.insecure_channel(address, options=list(options))
    return grpc.aio.secure_channel(address, channel_credentials(tls), options=list(options))


def sync_channel(address: str, options: Sequence[tuple[str, Any]] = ()) -> grpc.Channel:
    """A blocking channel to another service: TLS when this process has TLS settings."""
    tls = process_tls()
    if tls is None:
        return grpc.insecure_channel(address, options=list(options))
    return grpc.secure_channel(address, channel_credentials(tls), options=list(options))
