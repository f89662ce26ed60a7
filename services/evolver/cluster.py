"""Mechanism-level failure clustering and medoid selection (Phase II stage 1).

Failures are partitioned by m* first (two failures that never got past different milestones are
different mechanisms), then, within one m*, by their signature at t_EOD: when in the episode it
happened (t_EOD over the budget), the object-relative state there (trace.relative_state, scaled
by I_succ), and the tools/recoveries active then. Within an m* the partition is complete-linkage
agglomerative clustering cut at ``radius``: every two members of a cluster are within it. The
medoid is the member with the least summed distance to the others.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from services.evolver.eod import EOD
from services.evolver.profile import Failure, SuccessIndex
from services.evolver.trace import STATE_DIM, Trace, relative_state


@dataclass(frozen=True)
class ClusterParams:
    """Complete-linkage cut (in scaled feature units), the weight of t_EOD's timing, and the most
    members a cluster may have (0: no limit)."""

    radius: float = 4.0
    time_weight: float = 4.0
    #: A cluster is one mechanism repaired together: its medoid gets the diagnosis and the gate asks
    #: its patches to solve every member (historical regression). Many dev seeds failing the same
    #: way make one huge cluster where a patch that solves 35 of 40 fails the gate; capped, the
    #: same failures form several tight clusters, each diagnosed and regressed on its own.
    max_size: int = 10


@dataclass
class Cluster:
    """Failures sharing one signature; ``medoid`` indexes ``members``."""

    cid: str
    m_star: str
    members: list[Failure]
    eods: list[EOD]
    features: np.ndarray
    medoid: int
    active_tools: list[str] = field(default_factory=list)

    @property
    def medoid_failure(self) -> Failure:
        """The cluster's representative failure."""
        return self.members[self.medoid]

    @property
    def seeds(self) -> list[int]:
        """Seeds of every member."""
        return [f.rollout.seed for f in self.members]


def active_tools(trace: Trace, step: int) -> list[str]:
    """Kinds of the interventions in control at env step ``step``."""
    kinds = []
    for iv in trace.interventions:
        start, end = int(iv.get("start_step", -1)), int(iv.get("end_step", 1 << 30) or 1 << 30)
        if start <= step <= end:
            kinds.append(str(iv.get("recovery") or iv.get("kind") or "intervention"))
    return sorted(set(kinds))


def signature(trace: Trace, eod: EOD, index: SuccessIndex, budget: int, tools: Sequence[str],
              vocabulary: Sequence[str], params: ClusterParams) -> np.ndarray:
    """The feature vector of one failure."""
    rel = relative_state(trace.obs)[eod.frame] / index.scale
    timing = np.array([params.time_weight * eod.step / max(budget, 1)])
    onehot = np.array([1.0 if v in tools else 0.0 for v in vocabulary])
    return np.concatenate([rel, timing, onehot]).astype(np.float64)


def medoid(features: np.ndarray) -> int:
    """Index of the row with the least summed Euclidean distance to the others."""
    d = np.linalg.norm(features[:, None, :] - features[None, :, :], axis=-1)
    return int(d.sum(axis=1).argmin())


def complete_linkage(features: np.ndarray, radius: float, max_size: int = 0) -> list[list[int]]:
    """Agglomerative clustering: merge the two clusters with the smallest maximum pairwise distance
    while it is at most ``radius``, never into one of more than ``max_size`` members (0: no limit).
    Deterministic; O(n^3), fine for tens of failures per m*."""
    d = np.linalg.norm(features[:, None, :] - features[None, :, :], axis=-1)
    groups = [[i] for i in range(len(features))]
    while len(groups) > 1:
        best, pair = np.inf, (0, 0)
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                if max_size and len(groups[a]) + len(groups[b]) > max_size:
                    continue
                link = d[np.ix_(groups[a], groups[b])].max()
                if link < best:
                    best, pair = link, (a, b)
        if best > radius:
            break
        a, b = pair
        groups[a] = sorted(groups[a] + groups[b])
        del groups[b]
    return sorted(groups, key=lambda g: (-len(g), g[0]))


def cluster_failures(failures: Sequence[Failure], traces: Sequence[Trace], eods: Sequence[EOD], index: SuccessIndex,
                     budget: int, params: ClusterParams = ClusterParams()) -> list[Cluster]:
    """Partition M_fail into clusters, largest first, each with its medoid."""
    tools = [active_tools(tr, e.step) for tr, e in zip(traces, eods)]
    vocabulary = sorted({t for ts in tools for t in ts})
    feats = np.stack([signature(tr, e, index, budget, ts, vocabulary, params)
                      for tr, e, ts in zip(traces, eods, tools)]) if failures else np.zeros((0, STATE_DIM + 1))
    clusters: list[Cluster] = []
    for m_star in sorted({f.m_star for f in failures}):
        rows = [i for i, f in enumerate(failures) if f.m_star == m_star]
        for group in complete_linkage(feats[rows], params.radius, params.max_size):
            idx = [rows[g] for g in group]
            sub = feats[idx]
            clusters.append(Cluster(cid="", m_star=m_star, members=[failures[i] for i in idx],
                                    eods=[eods[i] for i in idx], features=sub, medoid=medoid(sub),
                                    active_tools=sorted({t for i in idx for t in tools[i]})))
    clusters.sort(key=lambda c: (-len(c.members), c.m_star, c.seeds[0]))
    for n, c in enumerate(clusters):
        c.cid = f"K{n + 1}"
    return clusters
