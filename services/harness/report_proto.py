"""A harness episode report as its wire message (types.proto HarnessReport).

The env worker reports the harness of each episode it ran and the critic service the episodes it
judged remotely; both write the same message through this one function.
"""

from __future__ import annotations

from services.harness.runtime.engine import EpisodeReport
from zetta_wire.v1 import types_pb2


def report_to_proto(report: EpisodeReport, out: types_pb2.HarnessReport) -> None:
    """Write an EpisodeReport into its proto message."""
    out.harness, out.version, out.content_hash = report.harness, report.version, report.content_hash
    out.policy_actions, out.recovery_actions = report.policy_actions, report.recovery_actions
    for mode, n in report.actions_by_mode.items():
        out.actions_by_mode[mode] = n
    for iv in report.interventions:
        out.interventions.add(
            id=iv.id, kind=iv.kind, proposer=iv.proposer, evidence=iv.evidence, details=iv.details,
            decision=iv.decision, start_step=iv.start_step, end_step=iv.end_step, outcome=iv.outcome,
            actions=iv.actions, instruction=iv.instruction,
        )
    for kind, n in report.interventions_by_kind.items():
        out.interventions_by_kind[kind] = n
    for d in report.disabled_critics:
        out.disabled_critics.add(name=d.name, step=d.step, reason=d.reason)
    out.proposals, out.rejected = report.proposals, report.rejected
