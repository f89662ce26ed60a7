"""Optional LLM backend for repair: an OpenAI-compatible chat-completions endpoint proposes patches.

The model sees the repair spec, the parent harness and the library's templates with their
parameter ranges, and answers with JSON patches. A proposal is only a proposal: it becomes a
candidate after the same checks as the offline search (templates exist, parameters in range,
bounded edit, the critic fires near t_EOD on a diagnostic replay), then faces the same validation
and gates. The offline search never depends on it.
"""

from __future__ import annotations

import hashlib
import json
import os
import urllib.error
import urllib.request
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.evolver.diagnose import RepairSpec
from services.evolver.draft import CODE_TEMPLATE, CriticDraft, HarnessDraft
from services.evolver.repair import (Candidate, ReplayCase, SearchParams, check_patch, code_detector, library, plan_of,
                                     plan_redirect, plan_stages, playbooks, score_critic)
from services.evolver.replay import ReplayFailed, SandboxedCritic
from services.evolver.trace import Trace


class LLMError(RuntimeError):
    """The endpoint could not be reached or answered something that is not a patch list."""


@dataclass(frozen=True)
class LLMConfig:
    """Where the endpoint is (base URL up to /v1), which model, the key (may be empty), a timeout."""

    base_url: str
    model: str
    api_key: str = ""
    timeout_s: float = 60.0


def config_from_env() -> LLMConfig | None:
    """The optional backend of this process: ZETTA_EVOLVER_LLM_URL (+ _MODEL, _API_KEY); None when unset.
    The CLI and the evolver service read it the same way."""
    url = os.environ.get("ZETTA_EVOLVER_LLM_URL", "")
    if not url:
        return None
    model = os.environ.get("ZETTA_EVOLVER_LLM_MODEL", "")
    if not model:
        raise LLMError("ZETTA_EVOLVER_LLM_URL is set but ZETTA_EVOLVER_LLM_MODEL is not: name the model")
    return LLMConfig(url, model, os.environ.get("ZETTA_EVOLVER_LLM_API_KEY", ""))


def _prompt(spec: RepairSpec, parent: HarnessDraft, preds: Mapping[str, Any], recs: Mapping[str, Any]) -> str:
    def schema(entries: Mapping[str, Any]) -> dict[str, Any]:
        return {n: {k: [p.low, p.high, p.default] for k, p in e.params.items()} for n, e in entries.items()}

    return json.dumps({
        "task": "Propose up to 3 minimal harness patches for this failure cluster. Answer with only a JSON "
                "object {\"patches\": [{\"critic\": {\"template\": str, \"params\": {}}, \"recovery\": "
                "{\"template\": str, \"args\": {}}}]}. A recovery template is a recovery, an \"a+b\" chain of "
                "recoveries (args: one table per part) or a playbook. Templates and parameter ranges "
                "[low, high, default] below. Instead of a template a critic may be code: {\"code\": str, "
                "\"params\": {name: number}, \"evidence\": str}, Python defining detect(window, params) that "
                "returns a dict of evidence numbers when the failure shows, else None. It may import math, "
                "numpy, services.harness.runtime.api and services.harness.runtime.library (tools: vec, scalar, "
                "grasped, object_box, target_box, eef_object_dist, ...); window.frames[-1].obs holds "
                "proprioception (robot0_*), phi_* physical signals and milestones; objects only through "
                "frame.perceive('object'|'target'|'others').",
        "repair_spec": spec.to_dict(),
        "parent_critics": {k: {"template": c.template, "params": dict(c.params), "recovery": c.mode}
                           for k, c in parent.critics.items()},
        "predicates": schema(preds), "recoveries": schema(recs),
        "playbooks": {n: {"steps": list(b.steps), "for_first_missing_milestone_kinds": list(b.stages), "doc": b.doc}
                      for n, b in playbooks().items()},
    })


def ask(cfg: LLMConfig, content: str) -> str:
    """One chat completion; returns the assistant message text."""
    body = json.dumps({"model": cfg.model, "temperature": 0,
                       "messages": [{"role": "system", "content": "You repair robot harnesses. Reply with JSON only."},
                                    {"role": "user", "content": content}]}).encode()
    req = urllib.request.Request(cfg.base_url.rstrip("/") + "/chat/completions", data=body, method="POST",
                                 headers={"Content-Type": "application/json",
                                          **({"Authorization": f"Bearer {cfg.api_key}"} if cfg.api_key else {})})
    try:
        with urllib.request.urlopen(req, timeout=cfg.timeout_s) as resp:
            answer = json.loads(resp.read())
        return str(answer["choices"][0]["message"]["content"])
    except (urllib.error.URLError, OSError, KeyError, IndexError, ValueError) as exc:
        raise LLMError(f"{cfg.base_url}: no usable completion: {exc}") from None


def parse_patches(text: str) -> list[dict[str, Any]]:
    """The patch list in a reply (tolerates a fenced code block around the JSON)."""
    start, end = text.find("{"), text.rfind("}")
    if start < 0 or end <= start:
        raise LLMError("the reply holds no JSON object")
    try:
        patches = json.loads(text[start:end + 1]).get("patches")
    except (json.JSONDecodeError, AttributeError) as exc:
        raise LLMError(f"the reply is not a JSON patch object: {exc}") from None
    if not isinstance(patches, list):
        raise LLMError("the reply has no 'patches' list")
    return [p for p in patches if isinstance(p, dict)]


def propose(cfg: LLMConfig, spec: RepairSpec, parent: HarnessDraft, medoid: ReplayCase, members: Sequence[ReplayCase],
            successes: Sequence[Trace], params: SearchParams = SearchParams(),
            max_edits: int = 3, policy_instructions: Sequence[str] = ()) -> tuple[list[Candidate], list[str]]:
    """Candidates from the LLM that pass every offline check, and the reasons others were refused;
    ``policy_instructions`` as for repair.search."""
    preds, recs = library()
    accepted: list[Candidate] = []
    refused: list[str] = []
    for p in parse_patches(ask(cfg, _prompt(spec, parent, preds, recs))):
        cand, why = _candidate(p, spec, parent, medoid, members, successes, params, max_edits, policy_instructions)
        if cand is not None:
            accepted.append(cand)
        else:
            refused.append(why)
    return accepted, refused


def _candidate(patch: Mapping[str, Any], spec: RepairSpec, parent: HarnessDraft, medoid: ReplayCase,
               members: Sequence[ReplayCase], successes: Sequence[Trace], params: SearchParams,
               max_edits: int, policy_instructions: Sequence[str] = ()) -> tuple[Candidate | None, str]:
    """The candidate an LLM patch makes, or None and why it was refused (the search's own checks)."""
    from services.harness.runtime.library.schema import resolve

    preds, _ = library()
    if isinstance(patch.get("critic"), Mapping) and "code" in patch["critic"]:
        return _code_candidate(patch, spec, parent, medoid, members, successes, params, max_edits,
                               policy_instructions)
    try:
        template = str(patch["critic"]["template"])
        setting = {str(k): v for k, v in dict(patch["critic"].get("params", {})).items()}
        recovery = str(patch["recovery"]["template"])
        args = {str(k): v for k, v in dict(patch["recovery"].get("args", {})).items()}
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        return None, f"malformed patch {dict(patch)!r}: {exc}"
    plan = plan_of(recovery, args)
    critic = CriticDraft(template, setting, evidence=template, mode=recovery, missing=plan_stages(plan, spec.m_star))
    why = check_patch(parent, Candidate(f"c_{template}", critic, plan, -1, 0.0, 0.0, 0, source="llm"), max_edits)
    if why is not None:
        return None, why
    full = resolve(preds[template].params, setting, template)
    res = score_critic(preds[template].fn, full, medoid, members, successes, params.window, critic.missing,
                       redirect=plan_redirect(plan, policy_instructions))
    if res is None:
        return None, f"{template} does not fire within {params.window} steps of t_EOD on a replay of the medoid"
    if res[2] > params.max_false_positive:
        return None, f"{template} fires on {res[2]:.0%} of successful rollouts where its rule would grant it"
    critic = CriticDraft(template, full, evidence=template, mode=recovery, missing=plan_stages(plan, spec.m_star))
    edits = parent.with_patch({f"c_{template}": critic}, {template: plan}).edits_from(parent)
    return Candidate(f"c_{template}", critic, plan, res[0], res[1], res[2], edits, source="llm"), ""


def _code_candidate(patch: Mapping[str, Any], spec: RepairSpec, parent: HarnessDraft, medoid: ReplayCase,
                    members: Sequence[ReplayCase], successes: Sequence[Trace], params: SearchParams,
                    max_edits: int, policy_instructions: Sequence[str] = ()) -> tuple[Candidate | None, str]:
    """The candidate of a patch whose critic is code: rendered, loaded through the package loader's
    checks, built into a runtime (the signal whitelist), then replayed like a template."""
    from services.harness.package.errors import PackageRejected

    try:
        code = str(patch["critic"]["code"])
        setting = {str(k): v for k, v in dict(patch["critic"].get("params", {})).items()}
        recovery = str(patch["recovery"]["template"])
        args = {str(k): v for k, v in dict(patch["recovery"].get("args", {})).items()}
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        return None, f"malformed patch {dict(patch)!r}: {exc}"
    digest = hashlib.sha256(code.encode()).hexdigest()[:8]
    name = f"c_llm_{digest}"
    evidence = "".join(ch if ch.isalnum() else "_" for ch in str(patch["critic"].get("evidence") or name))[:40]
    plan = plan_of(recovery, args)
    critic = CriticDraft(CODE_TEMPLATE, setting, evidence=evidence, mode=recovery,
                         missing=plan_stages(plan, spec.m_star), code=code)
    cand = Candidate(name, critic, plan, -1, 0.0, 0.0, 0, source="llm")
    why = check_patch(parent, cand, max_edits)
    if why is not None:
        return None, why
    try:
        detect = code_detector(cand.apply(parent), name)
    except PackageRejected as exc:
        return None, f"package rejected: {exc}"
    except ReplayFailed as exc:
        return None, str(exc)
    try:
        res = score_critic(detect, setting, medoid, members, successes, params.window, critic.missing,
                           redirect=plan_redirect(plan, policy_instructions))
    except ReplayFailed as exc:
        return None, str(exc)  # raised, overran or crashed on a replay: recorded, the next patch goes on
    finally:
        if isinstance(detect, SandboxedCritic):
            detect.close()
    if res is None:
        return None, f"{name} does not fire within {params.window} steps of t_EOD on a replay of the medoid"
    if res[2] > params.max_false_positive:
        return None, f"{name} fires on {res[2]:.0%} of successful rollouts where its rule would grant it"
    edits = cand.apply(parent).edits_from(parent)
    return Candidate(name, critic, plan, res[0], res[1], res[2], edits, source="llm"), ""
