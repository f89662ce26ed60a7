"""Top-down hierarchical causal diagnosis of a cluster's medoid (Phase II stage 1).

The layers are inspected in the paper's order, eval -> critic -> state -> plan -> recovery ->
param, and the diagnosis stops at the first (highest) layer whose check explains the failure:
if higher-level logic accounts for it, lower-level parameters are never touched. Each check is a
plain function of the medoid's trace, its t_EOD and what the current harness did (interventions
recorded in the trace, critic firings from a diagnostic replay), so the order is testable and
every conclusion carries its evidence chain. The chosen layer is then checked on the other
members of the cluster (consistency) and written out as a repair specification.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.evolver.eod import EOD
from services.evolver.trace import Trace

LAYERS = ("eval", "critic", "state", "plan", "recovery", "param")
#: Intervention outcomes (services/harness/runtime/engine.py) that mean the recovery did its job.
REENTERED = frozenset({"reentered"})


@dataclass(frozen=True)
class Case:
    """What the diagnosis sees of one failure.

    ``fired`` maps each critic of the current harness to the env step it first fired on a replay of
    this trace (None: silent); ``detectable`` maps library predicate templates to the step they
    would first fire (None: silent) at default parameters."""

    trace: Trace
    eod: EOD
    success: bool
    m_star: str
    fired: Mapping[str, int | None] = field(default_factory=dict)
    detectable: Mapping[str, int | None] = field(default_factory=dict)
    window: int = 40


@dataclass(frozen=True)
class Finding:
    """A layer's verdict: whether it explains the failure, and why."""

    layer: str
    explains: bool
    evidence: tuple[str, ...] = ()


def _near(step: int | None, eod: EOD, window: int) -> bool:
    """Whether a firing at ``step`` catches the divergence: within ``window`` steps of t_EOD, or, when
    t_EOD had no reference to locate it (the closest-approach fallback), anywhere up to it: an
    earlier firing is then a precursor, not a miss."""
    if step is None:
        return False
    return abs(step - eod.step) <= window if eod.referenced else step <= eod.step + window


def _intervention_at(trace: Trace, step: int, window: int) -> dict[str, Any] | None:
    for iv in trace.interventions:
        start = int(iv.get("start_step", -1))
        end = int(iv.get("end_step", 0) or 1 << 30)
        if start - window <= step <= end:
            return iv
    return None


def check_eval(c: Case) -> Finding:
    """Success criteria vs milestones: every goal milestone seen but no success (or the reverse)."""
    all_seen = c.m_star in ("", "<none>")
    if all_seen and not c.success:
        return Finding("eval", True, ("every milestone of M was observed but the success predicate never held",))
    if c.success and not all_seen:
        return Finding("eval", True, (f"success reported while milestone {c.m_star} was never observed",))
    return Finding("eval", False)


def check_critic(c: Case) -> Finding:
    """Critic false negative (no critic fired near t_EOD although a library predicate would) or false
    positive (an intervention began while the state was still nominal, and the episode failed)."""
    iv = _intervention_at(c.trace, c.eod.step, c.window)
    fired_near = [n for n, s in c.fired.items() if _near(s, c.eod, c.window)]
    if iv is not None and int(iv.get("start_step", 0)) < c.eod.step - c.window:
        return Finding("critic", True, (f"false positive: {iv.get('critic', '?')} took over at step "
                                        f"{iv.get('start_step')} before the divergence at {c.eod.step}",))
    if iv is None and not fired_near:
        detect = sorted(n for n, s in c.detectable.items() if _near(s, c.eod, c.window))
        if detect:
            return Finding("critic", True, (f"false negative: no critic fired within {c.window} steps of t_EOD="
                                            f"{c.eod.step} (m*={c.m_star})", f"library predicates that fire there: "
                                            f"{', '.join(detect)}"))
    return Finding("critic", False)


def check_state(c: Case) -> Finding:
    """State representation: the published task state contradicts itself at t_EOD."""
    k = c.eod.frame
    obs = c.trace.obs
    issues = []
    if "task_object_pos" in obs and not np.any(obs["task_object_pos"][k]):
        issues.append("task object position unbound (zeros) at t_EOD")
    if "phi_grasp" in obs and "phi_finger_contact" in obs:
        if obs["phi_grasp"][k][0] > 0.5 and obs["phi_finger_contact"][k].sum() < 2:
            issues.append("grasp flag set while a finger reports no contact")
    return Finding("state", bool(issues), tuple(issues))


def check_plan(c: Case) -> Finding:
    """Planning/control: the commanded motion was not realized (blocked) or collisions rose around
    t_EOD although critics saw the failure coming."""
    obs = c.trace.obs
    lo, hi = max(0, c.eod.frame - 3), min(c.trace.frames, c.eod.frame + 4)
    issues = []
    if "phi_eef_motion" in obs:
        m = obs["phi_eef_motion"][lo:hi]
        cmd = np.linalg.norm(m[:, :3], axis=1)
        real = np.linalg.norm(m[:, 3:], axis=1)
        if len(cmd) and cmd.mean() > 1e-3 and real.mean() < 0.25 * cmd.mean():
            issues.append(f"commanded motion {cmd.mean():.4f} m/step realized only {real.mean():.4f}: blocked")
    if "phi_collision_intensity" in obs and len(obs["phi_collision_intensity"][lo:hi]):
        peak = float(obs["phi_collision_intensity"][lo:hi].max())
        if peak > 50.0:
            issues.append(f"collision intensity {peak:.0f} N around t_EOD")
    return Finding("plan", bool(issues), tuple(issues))


def check_recovery(c: Case) -> Finding:
    """Recovery: the failure happened while a recovery was in control, or a recovery ended failed."""
    iv = _intervention_at(c.trace, c.eod.step, 0)
    if iv is not None:
        return Finding("recovery", True, (f"recovery {iv.get('recovery', '?')} was in control at t_EOD",))
    failed = [iv for iv in c.trace.interventions if str(iv.get("outcome", "")) not in REENTERED]
    if failed:
        return Finding("recovery", True, (f"{len(failed)} recoveries ended with outcome "
                                          f"{failed[0].get('outcome')}",))
    return Finding("recovery", False)


def check_param(c: Case) -> Finding:
    """Parameters: a critic fired and its recovery handed back, yet the failure came anyway (too late,
    too early or too weak: thresholds)."""
    if c.trace.interventions or any(s is not None for s in c.fired.values()):
        return Finding("param", True, (f"the harness intervened ({len(c.trace.interventions)} interventions) but "
                                       f"the episode still failed at m*={c.m_star}",))
    return Finding("param", False)


CHECKS: tuple[Callable[[Case], Finding], ...] = (check_eval, check_critic, check_state, check_plan, check_recovery,
                                                 check_param)


@dataclass(frozen=True)
class RepairSpec:
    """The diagnosis of a cluster: the root layer L*, its evidence, and what a patch must do."""

    cluster: str
    layer: str
    m_star: str
    t_eod: int
    medoid: str
    evidence: tuple[str, ...]
    consistency: float
    findings: tuple[Finding, ...]
    detect_near: tuple[str, ...] = ()

    @property
    def repairable(self) -> bool:
        """Whether the harness can be patched for it (eval errors and unexplained failures cannot)."""
        return self.layer in ("critic", "state", "plan", "recovery", "param")

    def to_dict(self) -> dict[str, Any]:
        """JSON form for the manifest and the report."""
        return {"cluster": self.cluster, "layer": self.layer, "m_star": self.m_star, "t_eod": self.t_eod,
                "medoid": self.medoid, "evidence": list(self.evidence), "consistency": self.consistency,
                "inspected": [f.layer for f in self.findings], "detect_near": list(self.detect_near)}


def diagnose(case: Case) -> tuple[str, tuple[Finding, ...]]:
    """Walk the layers top-down; returns L* ("unexplained" if none) and the findings inspected."""
    findings = []
    for check in CHECKS:
        f = check(case)
        findings.append(f)
        if f.explains:
            return f.layer, tuple(findings)
    return "unexplained", tuple(findings)


def repair_spec(cluster: str, medoid_key: str, medoid: Case, others: Sequence[Case]) -> RepairSpec:
    """Diagnose the medoid, check the same layer on the other members, write the specification."""
    layer, findings = diagnose(medoid)
    check = dict(zip(LAYERS, CHECKS)).get(layer)
    agree = [check(o).explains for o in others] if check else []
    consistency = (1 + sum(agree)) / (1 + len(agree)) if layer != "unexplained" else 0.0
    near = tuple(sorted(n for n, s in medoid.detectable.items() if _near(s, medoid.eod, medoid.window)))
    return RepairSpec(cluster, layer, medoid.m_star, medoid.eod.step, medoid_key,
                      findings[-1].evidence if layer != "unexplained" else (), consistency, findings, near)
