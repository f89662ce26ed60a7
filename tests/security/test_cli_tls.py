"""The `zetta` command line against a stack with TLS (and auth) on, as a user at a workstation
runs it: `zetta harness` reaches the critic service with the CA and a client certificate (mutual
TLS), `zetta workers` the gateway with the CA and a token, from the same variables or flags the
SDK takes (zetta.ClientCredentials). Certificates are made by the test (scripts/make_certs.sh).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from services.ops.local_stack import LocalStack
from tests.security.test_auth_tls import TOKENS, tokens_file
from tests.unit.test_harness_package import example_files, write_tree

ROOT = Path(__file__).resolve().parents[2]
#: Variables the command line reads; cleared so only what each call passes counts.
CLIENT_VARS = ("ZETTA_TOKEN", "ZETTA_TOKEN_FILE", "ZETTA_TLS_CA", "ZETTA_TLS_CERT", "ZETTA_TLS_KEY", "ZETTA_CRITIC_ADDR")


def zetta(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run `zetta ARGS` (python -m services.ops.cli) with ``env`` on top of a clean environment."""
    base = {k: v for k, v in os.environ.items() if k not in CLIENT_VARS}
    base["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python")])
    return subprocess.run([sys.executable, "-m", "services.ops.cli", *args], cwd=ROOT, env={**base, **(env or {})},
                          capture_output=True, text=True, timeout=120)


@pytest.fixture
def certs(tmp_path: Path) -> Path:
    """A CA, a certificate for the services and one for the command-line user."""
    out = tmp_path / "certs"
    subprocess.run([str(ROOT / "scripts" / "make_certs.sh"), str(out), "service", "cli-user"], check=True,
                   capture_output=True)
    return out


@pytest.fixture
def tls_stack(stack_factory: Callable[..., LocalStack], certs: Path, tmp_path: Path) -> LocalStack:
    """Every service on TLS (mutual between services), the gateway with tokens."""
    return stack_factory(env_workers=1, slots=1, families=("robosuite",), client_token=TOKENS["ops"][1], extra_env={
        "ZETTA_TLS_CERT": str(certs / "service.pem"), "ZETTA_TLS_KEY": str(certs / "service-key.pem"),
        "ZETTA_TLS_CA": str(certs / "ca.pem"), "ZETTA_AUTH_TOKENS_FILE": str(tokens_file(tmp_path)),
        "ZETTA_WORKER_TOKEN": TOKENS["pool"][1]})


def test_harness_cli_over_mutual_tls(tls_stack: LocalStack, certs: Path, tmp_path: Path) -> None:
    """publish, list and get over TLS with the client certificate from the variables or the flags;
    without a client certificate or without TLS the command fails with the service's status."""
    package = write_tree(tmp_path / "pkg", example_files(name="cli-tls"))
    critic = ["harness", "--critic", tls_stack.critic_address]
    client_env = {"ZETTA_TLS_CA": str(certs / "ca.pem"), "ZETTA_TLS_CERT": str(certs / "cli-user.pem"),
                  "ZETTA_TLS_KEY": str(certs / "cli-user-key.pem")}

    published = zetta(*critic, "publish", str(package), env=client_env)
    assert published.returncode == 0, published.stderr
    assert "published cli-tls@1" in published.stdout
    listed = zetta(*critic, "list", env=client_env)
    assert listed.returncode == 0 and "cli-tls@1" in listed.stdout, listed.stderr
    # The same with flags instead of variables.
    flags = ["--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / "cli-user.pem"),
             "--tls-key", str(certs / "cli-user-key.pem")]
    got = zetta(*critic, *flags, "get", "cli-tls@1", "--out", str(tmp_path / "out"))
    assert got.returncode == 0, got.stderr
    assert (tmp_path / "out" / "SKILL.md").read_bytes() == (package / "SKILL.md").read_bytes()

    # The critic service requires a client certificate: the CA alone is refused.
    no_cert = zetta(*critic, "--tls-ca", str(certs / "ca.pem"), "list")
    assert no_cert.returncode == 1 and "zetta harness list: UNAVAILABLE" in no_cert.stderr, no_cert.stderr
    plaintext = zetta(*critic, "list")
    assert plaintext.returncode == 1 and "UNAVAILABLE" in plaintext.stderr
    # Half a client certificate is a usage error, said before dialing.
    half = zetta(*critic, "--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / "cli-user.pem"), "list")
    assert half.returncode == 1 and "needs its key" in half.stderr


def test_gateway_commands_over_tls_with_a_token(tls_stack: LocalStack, certs: Path, tmp_path: Path) -> None:
    """`zetta workers` and `zetta sessions` with the CA and the token (variable or file)."""
    gateway = ["--gateway", tls_stack.gateway_address]
    token_file = tmp_path / "alice.token"
    token_file.write_text(TOKENS["alice"][1] + "\n")
    env = {"ZETTA_TLS_CA": str(certs / "ca.pem"), "ZETTA_TOKEN": TOKENS["alice"][1]}

    workers = zetta("workers", *gateway, env=env)
    assert workers.returncode == 0, workers.stderr
    assert "env-0" in workers.stdout and "alive" in workers.stdout
    sessions = zetta("sessions", *gateway, "--tls-ca", str(certs / "ca.pem"), "--token-file", str(token_file))
    assert sessions.returncode == 0, sessions.stderr

    no_token = zetta("workers", *gateway, "--tls-ca", str(certs / "ca.pem"))
    assert no_token.returncode == 1 and "zetta workers: UNAUTHENTICATED" in no_token.stderr, no_token.stderr
    plaintext = zetta("workers", *gateway, env={"ZETTA_TOKEN": TOKENS["alice"][1]})
    assert plaintext.returncode == 1 and "UNAVAILABLE" in plaintext.stderr
