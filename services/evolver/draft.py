"""A harness version as the evolver composes it, before it is written as a package directory.

The offline search writes no code: its critics are library predicate templates with bounded
parameters, every plan maps an evidence kind to a library recovery with its arguments. A critic
proposed by the LLM backend may be code instead (``CriticDraft.code``: a ``detect(window, params)``
function); it is rendered as tools/<name>.py and goes through the same loader checks (imports,
forbidden names), the runtime's signal whitelist and its sandboxed call budget as any package code;
the evolver imports and replays it only in a harness sandbox child (services/evolver/replay.py).
:func:`render` turns a draft into the agreed package files (SKILL.md with TOML front matter that
declares library critics and adjudication rules, tools/*.py and params/*.toml for code critics,
plans/*.toml playbooks); the critic service hashes, checks and versions them.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any


@dataclass(frozen=True)
class CriticDraft:
    """A critic: predicate template, its parameters, the evidence kind it emits and the mode it
    suggests (the recovery that handles that evidence)."""

    template: str
    params: Mapping[str, float]
    evidence: str
    mode: str
    priority: int = 10
    #: Kinds of first missing milestone (e.g. "on", "grasped") under which the orchestrator may
    #: grant the recovery: the task knowledge that keeps a critic from acting out of its stage.
    missing: tuple[str, ...] = ()
    #: Python source defining ``detect(window, params)`` (evidence numbers, or None) for a critic
    #: an LLM wrote; "" for a library predicate critic. ``template`` is then :data:`CODE_TEMPLATE`.
    code: str = ""


@dataclass(frozen=True)
class PlanDraft:
    """A playbook entry: evidence kind -> recovery template ("a+b": a, then b) and arguments (for a
    chain: one table per part, by part name)."""

    recovery: str
    args: Mapping[str, Any] = field(default_factory=dict)
    max_uses: int = 3
    #: Actions the intervention may take, the wait for re-entry included: a recovery that cannot
    #: clear its evidence gives control back after this many instead of holding to the episode's end
    #: (the runtime's cap, services/harness/runtime/limits.py; playbooks may set less).
    max_steps: int = 80
    #: Library predicate that must hold before re-entry ("" = none).
    clear_when: str = ""
    #: The library playbook this plan instantiates ("" = a bare recovery template); names the mode.
    playbook: str = ""


@dataclass(frozen=True)
class HarnessDraft:
    """Everything a package holds, in evolver terms."""

    name: str
    tasks: tuple[str, ...]
    critics: Mapping[str, CriticDraft] = field(default_factory=dict)
    plans: Mapping[str, PlanDraft] = field(default_factory=dict)
    reentry_gamma: float = 0.6
    reentry_k: int = 5
    #: Runtime settings: frames critics see (at least every critic's horizon) and the quiet steps
    #: after an intervention, so the policy gets the chance re-entry promised it before the old
    #: evidence still in the window counts again.
    window: int = 80
    cooldown: int = 15
    description: str = "Harness evolved by Zetta from a frozen policy's failures."

    def with_patch(self, critics: Mapping[str, CriticDraft], plans: Mapping[str, PlanDraft]) -> "HarnessDraft":
        """This draft with critics and plans added or replaced."""
        return replace(self, critics={**self.critics, **critics}, plans={**self.plans, **plans})

    def fingerprint(self) -> str:
        """Identity of the draft's behaviour on its tasks (not its name), for the buffer of rejected
        candidates: a patch refused on one task may still be the answer on another."""
        body = {"tasks": list(self.tasks), "critics": {k: [v.template, dict(sorted(v.params.items())), v.evidence, v.mode, v.priority, list(v.missing)]
                            + ([hashlib.sha256(v.code.encode()).hexdigest()] if v.code else [])
                            for k, v in sorted(self.critics.items())},
                "plans": {k: [v.recovery, dict(sorted(v.args.items())), v.max_uses, v.max_steps, v.clear_when]
                          for k, v in sorted(self.plans.items())},
                "reentry": [self.reentry_gamma, self.reentry_k], "runtime": [self.window_frames(), self.cooldown]}
        return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()[:16]

    def window_frames(self) -> int:
        """The runtime window: ``window``, widened past every critic's integer parameters (frame
        counts: horizon, confirm, ...) so no critic is starved of the frames it looks back over."""
        from services.harness.runtime.library import PREDICATES

        frames = [int(v) + 1 for c in self.critics.values() if c.template in PREDICATES
                  for k, v in c.params.items() if k in PREDICATES[c.template].params
                  and PREDICATES[c.template].params[k].kind == "int"]
        return max([self.window, *frames])

    def edits_from(self, parent: "HarnessDraft") -> int:
        """How many critics/plans/parameters differ from ``parent`` (the size of the patch)."""
        n = 0
        for k in set(self.critics) | set(parent.critics):
            a, b = self.critics.get(k), parent.critics.get(k)
            if a is None or b is None or a.template != b.template or a.code != b.code:
                n += 1
            else:
                n += sum(1 for p in set(a.params) | set(b.params) if a.params.get(p) != b.params.get(p))
        for k in set(self.plans) | set(parent.plans):
            a2, b2 = self.plans.get(k), parent.plans.get(k)
            if a2 is None or b2 is None or a2.recovery != b2.recovery:
                n += 1
            else:
                n += sum(1 for p in set(a2.args) | set(b2.args) if a2.args.get(p) != b2.args.get(p))
                n += (a2.max_uses != b2.max_uses) + (a2.max_steps != b2.max_steps) + (a2.clear_when != b2.clear_when)
        return n


#: The template name of a code critic (one an LLM wrote), which no library predicate has.
CODE_TEMPLATE = "code"


def code_module(name: str, critic: CriticDraft, mode: str) -> str:
    """tools/<name>.py of a code critic: its ``detect`` and the critic function that wraps it."""
    return (f"from services.harness.runtime.api import Proposal\n\n{critic.code.strip()}\n\n\n"
            f"def critic_main(window, params):\n"
            f"    \"\"\"Proposes {critic.evidence} whenever detect() returns evidence numbers.\"\"\"\n"
            f"    details = detect(window, params)\n"
            f"    return None if details is None else Proposal({json.dumps(name + '.main')}, "
            f"{json.dumps(critic.evidence)}, {json.dumps(mode)}, dict(details))\n")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return _inline(v)
    return json.dumps(str(v))


def _inline(values: Mapping[str, Any]) -> str:
    return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in sorted(values.items())) + " }"


def mode_name(evidence: str, plan: PlanDraft) -> str:
    """The playbook (mode) name of a plan: one per evidence kind."""
    return f"{plan.playbook or plan.recovery.replace('+', '_then_')}_on_{evidence}"


def render(draft: HarnessDraft) -> dict[str, bytes]:
    """The package files of a draft (without manifest.json, which the registry writes).

    Critics are library-predicate critics declared in SKILL.md ``[[critics]]`` (no code), each
    with an ``[[adjudication]]`` rule that grants its playbook, gated on the kind of the cluster's
    first missing milestone; plans/<mode>.toml holds the playbook."""
    front = [f"name = {json.dumps(draft.name)}", f"description = {json.dumps(draft.description)}",
             f"tasks = {_toml_value(list(draft.tasks))}", "", "[runtime]", f"window = {draft.window_frames()}",
             f"cooldown = {draft.cooldown}", "", "[reentry]", f"gamma = {draft.reentry_gamma!r}",
             f"k = {draft.reentry_k}", ""]
    files: dict[str, bytes] = {}
    for name, c in sorted(draft.critics.items()):
        plan = draft.plans.get(c.evidence)
        mode = mode_name(c.evidence, plan) if plan else c.mode
        if c.code:
            files[f"tools/{name}.py"] = code_module(name, c, mode).encode()
            files[f"params/{name}.toml"] = "".join(f"{k} = {_toml_value(v)}\n" for k, v in sorted(c.params.items())).encode()
        else:
            front += ["[[critics]]", f"name = {json.dumps(name)}", f"predicate = {json.dumps(c.template)}",
                      f"evidence = {json.dumps(c.evidence)}", f"mode = {json.dumps(mode)}",
                      f"params = {_inline(c.params)}", ""]
        front += ["[[adjudication]]", f"evidence = {json.dumps(c.evidence)}", f"mode = {json.dumps(mode)}",
                  f"priority = {c.priority}"] + ([f"missing = {_toml_value(list(c.missing))}"] if c.missing else []) + [""]
    body = "\n# Evolved harness\n\nCritics: " + (", ".join(f"`{k}` ({c.template} -> {c.evidence})"
                                                     for k, c in sorted(draft.critics.items())) or "none") + ".\n"
    files["SKILL.md"] = ("+++\n" + "\n".join(front) + "\n+++\n" + body).encode()
    for evidence, p in sorted(draft.plans.items()):
        mode = mode_name(evidence, p)
        parts = p.recovery.split("+")
        recovery = json.dumps(parts[0]) if len(parts) == 1 else _toml_value(parts)
        text = f"[{mode}]\nrecovery = {recovery}\nmax_uses = {p.max_uses}\nmax_steps = {p.max_steps}\n"
        if p.clear_when:
            text += f"clear_when = {json.dumps(p.clear_when)}\n"
        if p.args:
            text += f"params = {_inline(p.args)}\n"
        files[f"plans/{mode}.toml"] = text.encode()
    return files
