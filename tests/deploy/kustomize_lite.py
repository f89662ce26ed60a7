"""A small kustomize for the features deploy/k8s uses, so the manifests render without kubectl.

PyPI carries no kustomize and `kubectl` is not on every machine. This renders a kustomization
directory with exactly the fields deploy/k8s uses and refuses any other field, so a manifest change
that needs more cannot pass silently:

- ``resources``: files (multi-document YAML) and directories holding a kustomization.yaml;
- ``namespace``: set on every namespaced object (and as the name of a Namespace object);
- ``images``: ``name`` -> ``newName`` / ``newTag`` for containers and initContainers;
- ``patches``: inline RFC 6902 JSON patches (add, remove, replace, test) with a ``target`` of
  group / version / kind / name;
- ``configMapGenerator``: ``name``, ``files`` (``path`` or ``key=path``, relative to the
  kustomization directory and inside it) and ``options.labels``, with ``generatorOptions``
  ``disableNameSuffixHash: true`` (the content-hash suffix is not implemented, so it is refused).

Where ``kubectl kustomize`` exists, tests/deploy renders with both and requires the same objects.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

SUPPORTED = {"apiVersion", "kind", "resources", "namespace", "images", "patches", "configMapGenerator",
             "generatorOptions"}
CLUSTER_SCOPED = {"Namespace", "ClusterRole", "ClusterRoleBinding", "PriorityClass", "StorageClass",
                  "CustomResourceDefinition", "PersistentVolume"}


class KustomizeError(ValueError):
    """The kustomization uses something this renderer does not support, or a patch fails."""


def render(directory: Path) -> list[dict[str, Any]]:
    """The objects a kustomization directory produces."""
    directory = Path(directory)
    spec = yaml.safe_load((directory / "kustomization.yaml").read_text()) or {}
    unknown = set(spec) - SUPPORTED
    if unknown:
        raise KustomizeError(f"{directory}: unsupported kustomization fields {sorted(unknown)}")
    objects: list[dict[str, Any]] = []
    for entry in spec.get("resources", []):
        path = (directory / entry).resolve()
        if path.is_dir():
            objects.extend(render(path))
        else:
            objects.extend(d for d in yaml.safe_load_all(path.read_text()) if d)
    objects.extend(_generate_config_maps(spec, directory))
    for patch in spec.get("patches", []):
        _apply_patch(objects, patch, directory)
    for image in spec.get("images", []):
        _set_image(objects, image)
    if "namespace" in spec:
        for obj in objects:
            if obj["kind"] == "Namespace":
                obj["metadata"]["name"] = spec["namespace"]
            elif obj["kind"] not in CLUSTER_SCOPED:
                obj["metadata"]["namespace"] = spec["namespace"]
    return objects


def _generate_config_maps(spec: dict[str, Any], directory: Path) -> list[dict[str, Any]]:
    generators = spec.get("configMapGenerator", [])
    options = spec.get("generatorOptions", {})
    if generators and options != {"disableNameSuffixHash": True}:
        raise KustomizeError(f"{directory}: only generatorOptions {{disableNameSuffixHash: true}} is supported")
    out = []
    for gen in generators:
        if set(gen) - {"name", "files", "options"} or set(gen.get("options", {})) - {"labels"}:
            raise KustomizeError(f"{directory}: unsupported configMapGenerator fields in {gen}")
        data = {}
        for entry in gen.get("files", []):
            name, sep, rel = entry.partition("=")
            rel = rel if sep else name
            path = (directory / rel).resolve()
            if not path.is_relative_to(directory.resolve()):
                raise KustomizeError(f"{directory}: {rel} is outside the kustomization (kustomize refuses it)")
            data[Path(name).name if not sep else name] = path.read_text()
        metadata: dict[str, Any] = {"name": gen["name"]}
        if gen.get("options", {}).get("labels"):
            metadata["labels"] = dict(gen["options"]["labels"])
        out.append({"apiVersion": "v1", "kind": "ConfigMap", "metadata": metadata, "data": data})
    return out


def _matches(obj: dict[str, Any], target: dict[str, Any]) -> bool:
    group, _, version = obj["apiVersion"].rpartition("/")
    wanted = {"group": group, "version": version, "kind": obj["kind"], "name": obj["metadata"]["name"]}
    return all(wanted[k] == v for k, v in target.items())


def _apply_patch(objects: list[dict[str, Any]], patch: dict[str, Any], directory: Path) -> None:
    if set(patch) - {"target", "patch"}:
        raise KustomizeError(f"{directory}: only inline patches with a target are supported: {patch}")
    target = patch["target"]
    if set(target) - {"group", "version", "kind", "name"}:
        raise KustomizeError(f"{directory}: unsupported patch target fields in {target}")
    ops = yaml.safe_load(patch["patch"])
    hits = [o for o in objects if _matches(o, target)]
    if not hits:
        raise KustomizeError(f"{directory}: patch target {target} matches nothing")
    for obj in hits:
        for op in ops:
            json_patch(obj, op)


def _tokens(path: str) -> list[str]:
    if not path.startswith("/"):
        raise KustomizeError(f"bad JSON pointer {path!r}")
    return [t.replace("~1", "/").replace("~0", "~") for t in path[1:].split("/")]


def json_patch(doc: dict[str, Any], op: dict[str, Any]) -> None:
    """Apply one RFC 6902 operation (add, remove, replace, test) in place."""
    *parents, last = _tokens(op["path"])
    node: Any = doc
    for tok in parents:
        node = node[int(tok)] if isinstance(node, list) else node[tok]
    kind = op["op"]
    if kind == "test":
        current = node[int(last)] if isinstance(node, list) else node.get(last)
        if current != op["value"]:
            raise KustomizeError(f"test failed at {op['path']}: {current!r} != {op['value']!r}")
    elif kind == "add":
        value = copy.deepcopy(op["value"])
        if isinstance(node, list):
            node.insert(len(node) if last == "-" else int(last), value)
        else:
            node[last] = value
    elif kind == "replace":
        if isinstance(node, list):
            node[int(last)] = copy.deepcopy(op["value"])
        else:
            if last not in node:
                raise KustomizeError(f"replace of missing {op['path']}")
            node[last] = copy.deepcopy(op["value"])
    elif kind == "remove":
        del node[int(last) if isinstance(node, list) else last]
    else:
        raise KustomizeError(f"unsupported JSON patch op {kind!r}")


def _split_image(image: str) -> tuple[str, str]:
    name, sep, tag = image.rpartition(":")
    if not sep or "/" in tag:
        return image, ""
    return name, tag


def _set_image(objects: list[dict[str, Any]], rule: dict[str, Any]) -> None:
    for obj in objects:
        pod = obj.get("spec", {}).get("template", {}).get("spec", {})
        for container in pod.get("containers", []) + pod.get("initContainers", []):
            name, tag = _split_image(container["image"])
            if name != rule["name"]:
                continue
            name = rule.get("newName", name)
            tag = rule.get("newTag", tag)
            container["image"] = f"{name}:{tag}" if tag else name


def key(obj: dict[str, Any]) -> tuple[str, str, str]:
    """Identity of an object: kind, namespace, name."""
    return obj["kind"], obj["metadata"].get("namespace", ""), obj["metadata"]["name"]
