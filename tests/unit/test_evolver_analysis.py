"""Loop 1 and Phase II stage 1 on constructed traces: I_succ, t_EOD, clustering, the medoid, and the
top-down diagnosis order."""

from __future__ import annotations

import numpy as np

from services.evolver.cluster import ClusterParams, cluster_failures, complete_linkage, medoid
from services.evolver.diagnose import LAYERS, Case, diagnose, repair_spec
from services.evolver.eod import EOD, EODParams, distances, t_eod
from services.evolver.profile import Failure, SuccessIndex, progress
from services.evolver.store import Rollout
from tests.unit.test_evolver_fixtures import make_trace


def rollout(seed: int, m_star: str) -> Rollout:
    return Rollout(key=f"g/6/{seed}/bare/profile", suite="g", task="6", seed=seed, init_state=seed % 50, split="dev",
                   harness="", purpose="profile", round=1, success=False, steps=58, first_missing=m_star,
                   milestones_reached=[], policy_steps=58, recovery_steps=0, interventions=0, trace_path="",
                   video_path="", wall_s=1.0)


def index() -> SuccessIndex:
    return SuccessIndex.build([make_trace("success", s) for s in range(4)])


def test_progress_counts_leading_milestones() -> None:
    """Progress is the number of leading milestones of M observed so far."""
    p = progress(make_trace("success"))
    assert p[0] == 0 and p[-1] == 5 and np.all(np.diff(p) >= 0)
    assert progress(make_trace("miss")).max() == 0


def test_eod_is_zero_on_success_and_finds_the_divergence() -> None:
    """A success stays near I_succ; a drop diverges after it loses the object (frame 22), not before;
    a miss diverges early, while heading for the wrong place."""
    idx = index()
    d_ok = distances(make_trace("success", 9), idx)
    assert np.isfinite(d_ok).all() and d_ok.max() < EODParams().epsilon
    drop = t_eod(make_trace("drop", 5), idx)
    assert drop.referenced and 20 <= drop.frame <= 24 and drop.step == 2 * drop.frame
    miss = t_eod(make_trace("miss", 5), idx)
    assert miss.referenced and miss.frame < 10


def test_eod_threshold_is_a_parameter() -> None:
    """A looser epsilon moves t_EOD later; one the failure never exceeds (it stays near the
    successes throughout) falls back to the closest approach, not to the end of the episode."""
    idx = index()
    tr = make_trace("drop", 5)
    tight, mid = t_eod(tr, idx, EODParams(epsilon=2.0)), t_eod(tr, idx, EODParams(epsilon=3.0))
    assert tight.referenced and mid.referenced and mid.frame >= tight.frame
    loose = t_eod(tr, idx, EODParams(epsilon=50.0))
    assert not loose.referenced and loose.frame == t_eod(tr, SuccessIndex.build([])).frame < tr.frames - 1


def test_eod_without_any_success_falls_back_to_the_closest_approach() -> None:
    """With an empty I_succ there is no reference: after the last milestone gain (lifted, frame 19)
    a drop diverges where the held object stopped nearing the target (the drop, frame 22); a miss
    where the hand came closest to the object before turning away."""
    e = t_eod(make_trace("drop", 1), SuccessIndex.build([]))
    assert not e.referenced and e.frame == 22 and e.progress == 3 and not np.isfinite(e.distance)
    m = t_eod(make_trace("miss", 1), SuccessIndex.build([]))
    assert not m.referenced and 3 <= m.frame <= 7 and m.progress == 0


def test_medoid_minimizes_summed_distance() -> None:
    """The medoid of points on a line is the middle one; of a tight group plus an outlier, a group member."""
    assert medoid(np.array([[0.0], [1.0], [2.0], [3.0], [4.0]])) == 2
    assert medoid(np.array([[0.0, 0], [0.1, 0], [0.05, 0.05], [9.0, 9.0]])) in (0, 1, 2)


def test_complete_linkage_cuts_at_the_radius() -> None:
    """Two tight groups far apart make two clusters, the larger first; a radius above the gap merges them."""
    f = np.array([[0.0], [0.1], [0.2], [5.0], [5.1]])
    assert complete_linkage(f, 1.0) == [[0, 1, 2], [3, 4]]
    assert complete_linkage(f, 10.0) == [[0, 1, 2, 3, 4]]


def test_complete_linkage_caps_the_cluster_size() -> None:
    """With a size cap the closest members still go together, but no cluster outgrows it."""
    f = np.array([[0.0], [0.1], [0.2], [0.3], [5.0]])
    assert complete_linkage(f, 10.0, max_size=2) == [[0, 1], [2, 3], [4]]
    assert complete_linkage(f, 10.0, max_size=4) == [[0, 1, 2, 3], [4]]


def test_failures_cluster_by_mechanism_with_a_member_medoid() -> None:
    """Misses and drops never share a cluster (different m*), and each cluster's medoid is a member."""
    idx = index()
    fails, traces = [], []
    for s in range(4):
        fails.append(Failure(rollout(s, "reached(a)"), "reached(a)"))
        traces.append(make_trace("miss", s))
    for s in range(4, 7):
        fails.append(Failure(rollout(s, "on(a,b)"), "on(a,b)"))
        traces.append(make_trace("drop", s))
    eods = [t_eod(t, idx) for t in traces]
    clusters = cluster_failures(fails, traces, eods, idx, budget=60, params=ClusterParams())
    assert [sorted(c.seeds) for c in clusters] == [[0, 1, 2, 3], [4, 5, 6]]
    assert [c.cid for c in clusters] == ["K1", "K2"]
    for c in clusters:
        assert len({f.m_star for f in c.members}) == 1
        assert c.medoid_failure in c.members


def test_clusters_under_the_gate_minimum_are_left_unrepaired() -> None:
    """Loop 2 takes up the largest clusters the regression gate could pass (3 seeds or more), up to
    its budget, and leaves the smaller ones, which no repair could get admitted."""
    from services.evolver.evolve import clusters_to_repair

    idx = index()
    fails, traces = [], []
    for s, (m, kind) in enumerate([("reached(a)", "miss")] * 4 + [("on(a,b)", "drop")] * 2):
        fails.append(Failure(rollout(s, m), m))
        traces.append(make_trace(kind, s))
    clusters = cluster_failures(fails, traces, [t_eod(t, idx) for t in traces], idx, budget=60)
    assert [len(c.members) for c in clusters] == [4, 2]
    chosen, small = clusters_to_repair(clusters, max_clusters=3, min_cluster=3)
    assert [c.cid for c in chosen] == ["K1"] and [c.cid for c in small] == ["K2"]
    chosen, small = clusters_to_repair(clusters, max_clusters=3, min_cluster=2)
    assert [c.cid for c in chosen] == ["K1", "K2"] and small == []
    assert [c.cid for c in clusters_to_repair(clusters, max_clusters=1, min_cluster=1)[0]] == ["K1"]


def _case(**kw: object) -> Case:
    base = dict(trace=make_trace("drop", 1), eod=EOD(22, 44, 9.0, 3, True), success=False, m_star="on(a,b)",
                fired={}, detectable={"grasp_lost": 46}, window=10)
    base.update(kw)
    return Case(**base)  # type: ignore[arg-type]


def test_diagnosis_stops_at_the_highest_layer_that_explains() -> None:
    """eval beats critic; critic (a false negative a library predicate would catch) beats the lower
    layers; when a critic fired in time and nothing else explains, param does; nothing: unexplained."""
    layer, findings = diagnose(_case(m_star="<none>"))
    assert layer == "eval" and [f.layer for f in findings] == ["eval"]
    layer, findings = diagnose(_case())
    assert layer == "critic" and [f.layer for f in findings] == ["eval", "critic"]
    assert "grasp_lost" in findings[-1].evidence[1]
    layer, findings = diagnose(_case(fired={"c_grasp_lost": 46}))
    assert layer == "param" and [f.layer for f in findings] == list(LAYERS)
    layer, _ = diagnose(_case(fired={}, detectable={}))
    assert layer == "unexplained"


def test_diagnosis_recovery_layer_when_a_recovery_was_in_control() -> None:
    """A failure inside a recovery's control interval is a recovery-layer failure (critic fired in time)."""
    tr = make_trace("drop", 1)
    tr.interventions.append({"critic": "c_grasp_lost", "recovery": "regrasp", "start_step": 40, "end_step": 50})
    layer, _ = diagnose(_case(trace=tr, fired={"c_grasp_lost": 40}))
    assert layer == "recovery"


def test_repair_spec_reports_consistency_over_the_cluster() -> None:
    """Consistency is the share of members the medoid's layer also explains."""
    spec = repair_spec("6/r1/K1", "key", _case(), [_case(), _case(detectable={})])
    assert spec.layer == "critic" and spec.repairable
    assert abs(spec.consistency - 2 / 3) < 1e-9 and spec.detect_near == ("grasp_lost",)
    assert not repair_spec("x", "k", _case(m_star="<none>"), []).repairable


def test_without_a_reference_an_earlier_firing_is_a_precursor() -> None:
    """Against a located t_EOD a critic must fire within the window; against the unreferenced
    fallback any firing up to it counts (the divergence cannot be placed more precisely)."""
    located = _case(eod=EOD(20, 200, 9.0, 0, True), detectable={"non_approach": 40})
    assert diagnose(located)[0] == "unexplained"
    fallback = _case(eod=EOD(20, 200, float("inf"), 0, False), detectable={"non_approach": 40})
    assert diagnose(fallback)[0] == "critic"
    from services.evolver.repair import ReplayCase

    tr = make_trace("miss")
    assert not ReplayCase(tr, 200, True).catches(40, 10) and ReplayCase(tr, 200, False).catches(40, 10)
    assert not ReplayCase(tr, 200, False).catches(260, 10) and not ReplayCase(tr, 200, False).catches(None, 10)
