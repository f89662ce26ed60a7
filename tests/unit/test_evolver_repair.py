"""Offline repair over the real harness library: bounded template search, replay, package checks,
consolidation, and the optional LLM backend against a tiny OpenAI-compatible server on loopback."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer

import pytest

from services.harness.package.loader import load_files
from services.harness.runtime.engine import HarnessRuntime
from services.harness.runtime.library import PREDICATES
from services.evolver.consolidate import consolidate
from services.evolver.diagnose import Case, repair_spec
from services.evolver.draft import CriticDraft, HarnessDraft, PlanDraft, render
from services.evolver.eod import t_eod
from services.evolver.llm import LLMConfig, LLMError, propose
from services.evolver.profile import SuccessIndex
from services.evolver.repair import (Candidate, ReplayCase, SearchParams, check_patch, param_grid, search, stage_of)
from services.evolver.replay import first_fire
from tests.unit.test_evolver_fixtures import make_trace

PARENT = HarnessDraft("evolved-6", ("6",))


def drop_cluster() -> tuple[object, ReplayCase, list[ReplayCase], list[object]]:
    idx = SuccessIndex.build([make_trace("success", s) for s in range(4)])
    drops = [make_trace("drop", s) for s in range(4, 8)]
    eods = [t_eod(t, idx) for t in drops]
    detect = {n: first_fire(drops[0], p.fn, {k: v.default for k, v in p.params.items()}) for n, p in PREDICATES.items()
              if n not in ("grasp_retained", "supported_placement")}
    spec = repair_spec("6/r1/K1", "key", Case(drops[0], eods[0], False, "on(a,b)", {}, detect, 40), [])
    medoid = ReplayCase(drops[0], eods[0].step)
    members = [ReplayCase(d, e.step) for d, e in zip(drops[1:], eods[1:])]
    return spec, medoid, members, [make_trace("success", 9)]


def test_param_grid_is_bounded_and_in_range() -> None:
    """Defaults first; every other setting moves at most max_edits parameters, never out of range."""
    schema = PREDICATES["non_approach"].params
    grid = param_grid(schema, max_edits=1, fraction=0.25)
    defaults = {k: p.default for k, p in schema.items()}
    assert grid[0] == defaults and len(grid) == 1 + 2 * len(schema)
    for g in grid:
        assert sum(g[k] != defaults[k] for k in g) <= 1
        assert all(schema[k].low <= v <= schema[k].high for k, v in g.items())
    assert max(sum(g[k] != defaults[k] for k in g) for g in param_grid(schema, 2, 0.25)) == 2


def test_search_finds_a_grasp_lost_critic_for_a_drop_cluster() -> None:
    """A drop cluster is a critic-layer false negative; the search pairs a grasp_lost critic that fires
    near t_EOD on every member, silent on successes, with a playbook that starts by acquiring the
    object again (never one that needs it in hand), granted at m*'s stage; the resulting package
    loads and builds a runtime."""
    spec, medoid, members, succ = drop_cluster()
    assert spec.layer == "critic"
    cands = search(spec, PARENT, medoid, members, succ, SearchParams(max_candidates=3))
    # The drop also shows as a hand that stops approaching the object: non_approach fires at t_EOD
    # too and leads; on the success it fires only once every milestone is reached, where no rule
    # grants anything, so it is no false positive there.
    assert [c.critic.template for c in cands[:2]] == ["non_approach", "grasp_lost"]
    assert cands[0].false_positive == 0.0 and cands[0].fire_step == medoid.t_eod
    best = cands[1]
    assert abs(best.fire_step - medoid.t_eod) <= 40 and best.coverage == 1.0 and best.false_positive == 0.0
    assert best.plan.playbook == "acquire" and best.plan.recovery == "regrasp" and "on" in best.critic.missing
    assert all(c.plan.playbook != "place" for c in cands)
    assert check_patch(PARENT, best, max_edits=3) is None
    runtime = HarnessRuntime(load_files(render(best.apply(PARENT))))
    assert [c.name for c in runtime.critics] == ["c_grasp_lost"]
    # The buffer of rejected candidates is honoured: a rejected harness is never proposed again.
    rejected = {c.apply(PARENT).fingerprint() for c in cands}
    again = search(spec, PARENT, medoid, members, succ, SearchParams(max_candidates=3), rejected.__contains__)
    assert not {c.apply(PARENT).fingerprint() for c in again} & rejected
    # ... for this task only: the same patch on another task's harness is a different candidate.
    other = HarnessDraft("evolved-9", ("9",))
    assert best in search(spec, other, medoid, members, succ, SearchParams(max_candidates=3), rejected.__contains__)


def test_false_positives_count_only_firings_a_rule_would_grant() -> None:
    """non_approach fires on the successful episode after its last milestone: gated on any stage,
    that firing is vetoed (nothing is missing), so it is no false positive; ungated it is one."""
    from services.evolver.repair import score_critic

    spec, medoid, members, succ = drop_cluster()
    pred = PREDICATES["non_approach"]
    defaults = {k: v.default for k, v in pred.params.items()}
    assert first_fire(succ[0], pred.fn, defaults) is not None
    assert first_fire(succ[0], pred.fn, defaults, stages=("on",)) is None
    ungated = score_critic(pred.fn, defaults, medoid, members, succ, 40)
    gated = score_critic(pred.fn, defaults, medoid, members, succ, 40, stages=("reached", "on"))
    assert ungated is not None and ungated[2] == 1.0
    assert gated is not None and gated[2] == 0.0 and gated[:2] == ungated[:2]


def test_patch_checks_refuse_unknown_templates_out_of_range_and_oversized_patches() -> None:
    """Every patch, searched or LLM-written, must name library templates with in-range parameters
    and stay within the edit bound."""
    ok = Candidate("c_grasp_lost", CriticDraft("grasp_lost", {"confirm": 3}, "grasp_lost", "regrasp"),
                   PlanDraft("regrasp"), 0, 1.0, 0.0, 2)
    assert check_patch(PARENT, ok, 3) is None
    bad_t = Candidate("c_x", CriticDraft("teleport", {}, "x", "regrasp"), PlanDraft("regrasp"), 0, 1, 0, 2)
    assert "unknown predicate" in (check_patch(PARENT, bad_t, 3) or "")
    bad_r = Candidate("c_grasp_lost", ok.critic, PlanDraft("magic"), 0, 1, 0, 2)
    assert "unknown recovery" in (check_patch(PARENT, bad_r, 3) or "")
    bad_p = Candidate("c_grasp_lost", CriticDraft("grasp_lost", {"confirm": 500}, "grasp_lost", "regrasp"),
                      PlanDraft("regrasp"), 0, 1, 0, 2)
    assert "outside" in (check_patch(PARENT, bad_p, 3) or "")
    assert "at most 1" in (check_patch(PARENT, ok, 1) or "")


def test_stage_of_is_the_milestone_kind() -> None:
    """Adjudication is gated on the kind of m*, which names no task object."""
    assert stage_of("on(wine_bottle_1,wine_rack_1)") == ("on",) and stage_of("<none>") == ()


def test_consolidation_stacks_in_order_and_earlier_clusters_keep_their_settings() -> None:
    """Within a cluster's stack a later patch replaces an earlier one of the same critic (it was
    validated on top of it); across clusters critics are unioned and, on a clash, the earlier
    (larger) cluster keeps the setting its historical regression measured."""
    a = Candidate("c_grasp_lost", CriticDraft("grasp_lost", {"confirm": 1}, "grasp_lost", "regrasp"),
                  PlanDraft("regrasp"), 44, 0.5, 0.0, 2)
    b = Candidate("c_grasp_lost", CriticDraft("grasp_lost", {"confirm": 3}, "grasp_lost", "release_and_restage"),
                  PlanDraft("release_and_restage"), 48, 1.0, 0.0, 2)
    c = Candidate("c_non_approach", CriticDraft("non_approach", {}, "non_approach", "pregrasp"), PlanDraft("pregrasp"),
                  10, 1.0, 0.0, 2)
    d = Candidate("c_grasp_lost", CriticDraft("grasp_lost", {"confirm": 5}, "grasp_lost", "regrasp"),
                  PlanDraft("regrasp"), 40, 1.0, 0.0, 2)
    merged = consolidate(PARENT, [[a, b], [c, d]])
    assert set(merged.critics) == {"c_grasp_lost", "c_non_approach"}
    assert merged.critics["c_grasp_lost"].params == {"confirm": 3}
    assert merged.plans["grasp_lost"].recovery == "release_and_restage"
    assert merged.plans["non_approach"].recovery == "pregrasp"
    assert consolidate(PARENT, []) == PARENT
    HarnessRuntime(load_files(render(merged)))


class _Handler(BaseHTTPRequestHandler):
    reply = ""
    seen: list[dict] = []

    def do_POST(self) -> None:
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        _Handler.seen.append({"path": self.path, "auth": self.headers.get("Authorization"), "body": body})
        out = json.dumps({"choices": [{"message": {"role": "assistant", "content": _Handler.reply}}]}).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(out)))
        self.end_headers()
        self.wfile.write(out)

    def log_message(self, *args: object) -> None:
        return None


@pytest.fixture
def llm_server() -> Iterator[str]:
    server = HTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/v1"
    server.shutdown()
    server.server_close()


def test_llm_patches_pass_the_same_checks(llm_server: str) -> None:
    """Of four proposed patches only the in-range grasp_lost one survives: an unknown template, an
    out-of-range parameter and a critic that never fires near t_EOD are refused with reasons."""
    spec, medoid, members, succ = drop_cluster()
    _Handler.reply = "```json\n" + json.dumps({"patches": [
        {"critic": {"template": "grasp_lost", "params": {"confirm": 2}}, "recovery": {"template": "regrasp", "args": {}}},
        {"critic": {"template": "teleport", "params": {}}, "recovery": {"template": "regrasp"}},
        {"critic": {"template": "grasp_lost", "params": {"confirm": 99}}, "recovery": {"template": "regrasp"}},
        {"critic": {"template": "held_near_target", "params": {}}, "recovery": {"template": "fine_alignment"}},
    ]}) + "\n```"
    cfg = LLMConfig(base_url=llm_server, model="tiny", api_key="k")
    accepted, refused = propose(cfg, spec, PARENT, medoid, members, succ)
    assert [(c.critic.template, c.critic.params["confirm"], c.source) for c in accepted] == [("grasp_lost", 2, "llm")]
    assert len(refused) == 3 and any("unknown predicate" in r for r in refused)
    assert any("outside" in r for r in refused) and any("does not fire" in r for r in refused)
    req = _Handler.seen[-1]
    assert req["path"] == "/v1/chat/completions" and req["auth"] == "Bearer k" and req["body"]["model"] == "tiny"
    assert "grasp_lost" in req["body"]["messages"][1]["content"]


def test_llm_errors_are_clear(llm_server: str) -> None:
    """A reply without patches, or no server at all, is an LLMError, never a silent empty result."""
    spec, medoid, members, succ = drop_cluster()
    _Handler.reply = "I cannot help with that."
    with pytest.raises(LLMError, match="no JSON"):
        propose(LLMConfig(llm_server, "tiny"), spec, PARENT, medoid, members, succ)
    with pytest.raises(LLMError, match="no usable completion"):
        propose(LLMConfig("http://127.0.0.1:9/v1", "tiny", timeout_s=2), spec, PARENT, medoid, members, succ)


#: A critic an LLM might write: the object was held, is no longer, and the gripper is still closed.
DROP_CODE = '''
from services.harness.runtime.library import tools


def detect(window, params):
    n = int(params["confirm"])
    frames = window.frames
    if len(frames) < n + 5 or any(tools.grasped(f) for f in frames[-n:]):
        return None
    held = sum(1 for f in frames[:-n] if tools.grasped(f))
    if held < 5 or tools.gripper_command(window.now.action) <= 0.0:
        return None
    return {"held_steps": float(held)}
'''


def test_llm_critic_code_passes_the_loader_the_signal_whitelist_and_the_replay(llm_server: str) -> None:
    """A critic written as code is rendered as tools/<name>.py, replayed like a template and, if it
    fires near t_EOD, becomes a candidate that builds a runtime; code that imports os or reads the
    simulator's boxes is refused with the loader's or the whitelist's reason."""
    spec, medoid, members, succ = drop_cluster()
    peek = "def detect(window, params):\n    return {'z': float(window.now.obs.get('task_object_bbox', [0])[0])}\n"
    _Handler.reply = json.dumps({"patches": [
        {"critic": {"code": DROP_CODE, "params": {"confirm": 3}, "evidence": "dropped"},
         "recovery": {"template": "acquire"}},
        {"critic": {"code": "import os\n\ndef detect(window, params):\n    return None\n", "params": {}},
         "recovery": {"template": "regrasp"}},
        {"critic": {"code": peek, "params": {}}, "recovery": {"template": "regrasp"}},
    ]})
    accepted, refused = propose(LLMConfig(llm_server, "tiny"), spec, PARENT, medoid, members, succ)
    assert len(accepted) == 1 and accepted[0].source == "llm" and accepted[0].critic.code == DROP_CODE
    cand = accepted[0]
    assert cand.critic.template == "code" and cand.critic.evidence == "dropped" and cand.plan.playbook == "acquire"
    assert abs(cand.fire_step - medoid.t_eod) <= 40
    files = render(cand.apply(PARENT))
    assert f"tools/{cand.critic_name}.py" in files and b"def critic_main" in files[f"tools/{cand.critic_name}.py"]
    runtime = HarnessRuntime(load_files(files))
    assert [c.name for c in runtime.critics] == [f"{cand.critic_name}.main"]
    assert any("'os' is not allowed" in r for r in refused) and any("task_object_bbox" in r for r in refused)
    assert "detect(window, params)" in _Handler.seen[-1]["body"]["messages"][1]["content"]
    # The code critic replays in its sandbox child with the same stage gating as a template: its
    # rule grants it at m*'s kind only when that is the one missing.
    from services.evolver.repair import code_detector
    from services.evolver.replay import SandboxedCritic

    detect = code_detector(cand.apply(PARENT), cand.critic_name)
    try:
        fire = first_fire(medoid.trace, detect, {}, start=medoid.start)
        assert fire is not None
        assert first_fire(medoid.trace, detect, {}, start=medoid.start, stages=("on",)) == fire
        assert first_fire(medoid.trace, detect, {}, start=medoid.start, stages=("reached_handle",)) is None
    finally:
        if isinstance(detect, SandboxedCritic):
            detect.close()
