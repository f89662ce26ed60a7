"""Readers for the deployment files, shared by the tests in tests/deploy.

- the compose files, merged the way `docker compose -f a -f b` merges them (for the mappings our
  overlays touch) and interpolated with their defaults;
- the Dockerfile: stages, and per target the ENV it inherits, CMD, USER, HEALTHCHECK and EXPOSE;
- the validators: found in the venv's bin/ first (where `make setup` installs them), then on PATH.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
DOCKERFILE = DEPLOY / "docker" / "Dockerfile"
COMPOSE = DEPLOY / "docker-compose.yml"
COMPOSE_GPU = DEPLOY / "docker-compose.gpu.yml"
COMPOSE_TEST = DEPLOY / "docker-compose.test.yml"
PROMETHEUS = DEPLOY / "prometheus"
GRAFANA = DEPLOY / "grafana"
K8S = DEPLOY / "k8s"
OVERLAYS = sorted(p for p in (K8S / "overlays").iterdir() if (p / "kustomization.yaml").exists())


def tool(name: str) -> str | None:
    """Path of a validator: the venv's bin/ (next to this interpreter, or ROOT/.venv), then PATH."""
    for d in (Path(sys.executable).parent, ROOT / ".venv" / "bin"):
        if (d / name).is_file() and os.access(d / name, os.X_OK):
            return str(d / name)
    return shutil.which(name)


# ---- compose ---------------------------------------------------------------------------------

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")


def _interpolate(value: Any, env: dict[str, str]) -> Any:
    if isinstance(value, str):
        return _VAR.sub(lambda m: env.get(m.group(1)) or (m.group(2) or ""), value)
    if isinstance(value, list):
        return [_interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: _interpolate(v, env) for k, v in value.items()}
    return value


def _merge(base: Any, over: Any) -> Any:
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = _merge(base[k], v) if k in base else v
        return out
    return over


def load_compose(*files: Path, env: dict[str, str] | None = None) -> dict[str, Any]:
    """The merged compose model of ``files`` (extension fields x-* dropped, ${VAR:-default} resolved)."""
    merged: dict[str, Any] = {}
    for f in files:
        merged = _merge(merged, yaml.safe_load(f.read_text()) or {})
    merged = {k: v for k, v in merged.items() if not k.startswith("x-")}
    return _interpolate(merged, env or {})


def environment(service: dict[str, Any]) -> dict[str, str]:
    """A service's environment as a mapping of strings."""
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


# ---- Dockerfile --------------------------------------------------------------------------------


@dataclass
class Stage:
    """One FROM ... AS name stage and the instructions that matter to the tests."""

    name: str
    base: str
    env: dict[str, str] = field(default_factory=dict)
    cmd: list[str] | None = None
    user: str | None = None
    workdir: str | None = None
    healthcheck: list[str] | None = None
    expose: list[str] = field(default_factory=list)
    instructions: list[tuple[str, str]] = field(default_factory=list)


def _logical_lines(text: str) -> list[str]:
    lines, current = [], ""
    for raw in text.splitlines():
        stripped = raw.strip()
        if not current and (not stripped or stripped.startswith("#")):
            continue
        if current and stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            current += stripped[:-1] + " "
            continue
        lines.append(current + stripped)
        current = ""
    if current:
        lines.append(current)
    return lines


def dockerfile_stages(path: Path = DOCKERFILE) -> dict[str, Stage]:
    """Stages by name, in order (ARGs before the first FROM are substituted into FROM)."""
    args: dict[str, str] = {}
    stages: dict[str, Stage] = {}
    stage: Stage | None = None
    for line in _logical_lines(path.read_text()):
        instr, _, rest = line.partition(" ")
        instr = instr.upper()
        rest = rest.strip()
        if instr == "ARG" and stage is None:
            k, _, v = rest.partition("=")
            args[k] = v
            continue
        if instr == "FROM":
            parts = rest.split()
            base = re.sub(r"\$\{(\w+)\}", lambda m: args.get(m.group(1), ""), parts[0])
            name = parts[2] if len(parts) >= 3 and parts[1].upper() == "AS" else f"stage{len(stages)}"
            stage = Stage(name=name, base=base)
            stages[name] = stage
            continue
        assert stage is not None, f"{path}: {instr} before FROM"
        stage.instructions.append((instr, rest))
        if instr == "ENV":
            for token in shlex.split(rest):
                k, _, v = token.partition("=")
                stage.env[k] = v
        elif instr == "CMD":
            stage.cmd = json.loads(rest)
        elif instr == "USER":
            stage.user = rest
        elif instr == "WORKDIR":
            stage.workdir = rest
        elif instr == "EXPOSE":
            stage.expose += rest.split()
        elif instr == "HEALTHCHECK":
            _, _, cmd = rest.partition("CMD ")
            stage.healthcheck = json.loads(cmd)
    return stages


def stage_chain(target: str, stages: dict[str, Stage] | None = None) -> list[Stage]:
    """The stages ``target`` is built on, base first."""
    stages = stages or dockerfile_stages()
    chain = []
    name: str | None = target
    while name in stages:
        chain.append(stages[name])
        name = stages[name].base
    return list(reversed(chain))


def image_config(target: str) -> Stage:
    """What an image of ``target`` runs with: ENV, CMD, USER, WORKDIR, HEALTHCHECK, EXPOSE inherited
    through its stages (ENV values may refer to earlier ones as $NAME)."""
    out = Stage(name=target, base="")
    for st in stage_chain(target):
        for k, v in st.env.items():
            out.env[k] = re.sub(r"\$(\w+)", lambda m: out.env.get(m.group(1), "$" + m.group(1)), v)
        out.cmd = st.cmd or out.cmd
        out.user = st.user or out.user
        out.workdir = st.workdir or out.workdir
        out.healthcheck = st.healthcheck or out.healthcheck
        out.expose = st.expose or out.expose
    return out
