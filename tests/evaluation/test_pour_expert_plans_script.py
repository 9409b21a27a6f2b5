"""benchmarks/pour_expert_plans.py and keygen.expert.pour_pinch.pinch_variants: every variant's full
cost agrees with the expert's own choice, the fixed-order counterfactual, the per-sector and per-cost
tallies on constructed plans, and refusing bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env
from keygen.expert import pour_pinch
from keygen.expert._pour_util import ReachChecker
from keygen.expert.pour import GOOD_ENOUGH, POUR_TURNS, PourExpert


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("pour_expert_plans")


def variant(turn: int, pitch: int, closing: int, lip: int, cost: float) -> dict:
    return {"turn_deg": turn, "pitch_deg": pitch, "closing": closing, "lip": lip, "cost": cost}


def test_first_within_keeps_the_cheapest_at_zero_and_the_preferred_within_the_tolerance(m) -> None:
    variants = [
        variant(45, 25, -1, -1, 0.30),
        variant(0, 55, 1, 1, 0.25),  # cheapest
        variant(0, 35, -1, -1, 0.40),  # preferred turn, jaws and lip, 0.15 over the cheapest
    ]
    assert m.first_within(variants, 0.0) is variants[1]
    assert m.first_within(variants, 0.1) is variants[1]  # only the cheapest is within 0.1
    assert m.first_within(variants, 0.2) is variants[2]  # turn 0 with the commonest jaws and lip
    assert m.first_within(variants, 10.0) is variants[2]
    with pytest.raises(ValueError):
        m.first_within([], 0.1)


def test_demo_summary_counts_plans_per_heading_sector(m) -> None:
    a, b = variant(0, 25, -1, -1, 0.0), variant(45, 55, -1, 1, 0.01)
    rows = [  # two plans near +y (90 degrees), one near +x
        {"heading_deg": 90.0, "plan": a, "variants": [a, b]},
        {"heading_deg": 95.0, "plan": b, "variants": [a | {"cost": 0.02}, b]},
        {"heading_deg": 80.0, "plan": a, "variants": [a, b]},
        {"heading_deg": 5.0, "plan": b, "variants": [b]},
    ]
    summary = m.demo_summary(rows, 4, [0.0, 0.05])
    north = summary["sectors"][1]
    assert (north["episodes"], north["distinct_plans"], north["commonest_share"]) == (3, 2, 0.667)
    assert north["distinct_plans_first_within_0"] == 2
    assert north["distinct_plans_first_within_0.05"] == 1  # b's scene also offers a within 0.02
    assert summary["sectors"][0]["distinct_plans"] == 1
    assert summary["sectors"][2]["episodes"] == 0 and summary["sectors"][2]["commonest_share"] is None
    assert summary["overall"]["distinct_plans"] == 2
    # At 0.05, a is kept over b where it costs 0.01 more: a mean 0.01 / 4 over the four scenes.
    assert summary["overall"]["mean_extra_cost_first_within_0.05"] == pytest.approx(0.01 / 4)


def test_eval_summary_tallies_successes_by_heading_and_by_plan_cost(m) -> None:
    cell = ("pour", "test", "hard", 1.0)
    plans = {
        (cell, 0, 1): {"heading_deg": 90.0, "cost": 0.0},
        (cell, 0, 2): {"heading_deg": 0.0, "cost": 0.9},
        (cell, 1, 3): {"heading_deg": 10.0, "cost": 2.0},
    }
    records = [
        {"_cell": cell, "object_id": 0, "seed": 1, "success": True},
        {"_cell": cell, "object_id": 0, "seed": 2, "success": False},
        {"_cell": cell, "object_id": 1, "seed": 3, "success": True},
    ]
    out = m.eval_summary({"p": records}, plans, 4)["p"]
    assert [t["episodes"] for t in out["by_sector"]] == [2, 1, 0, 0]
    assert [t["successes"] for t in out["by_sector"]] == [1, 1, 0, 0]
    assert [(t["episodes"], t["successes"]) for t in out["by_plan_cost"]] == [(1, 1), (0, 0), (0, 0), (2, 1)]
    assert out["by_plan_cost"][1]["ci95"] is None


def test_every_variant_costed_in_full_contains_the_experts_choice() -> None:
    env = make_env(EnvSpec("pour", "test", "hard", 1.0, image_size=64, num_points=256), 3)
    try:
        _, info = env.reset(seed=episode_seed(1000, 3, 0))
        anchors = {k: np.asarray(v, dtype=np.float64) for k, v in info["anchors"].items()}
        expert = PourExpert(grasp="pinch")
        chosen = expert.choose_plan(env, anchors)
        reach = ReachChecker(env.unwrapped.controller.handles)
        variants = pour_pinch.pinch_variants(env, anchors, reach, expert.scene_checker(env))
    finally:
        env.close()
    assert len(variants) == len(POUR_TURNS) * len(pour_pinch.PINCH_PITCHES) * 4
    same = [
        v
        for v in variants
        if (v.closing_sign, v.lip_side, v.pour_turn, v.pitch)
        == (chosen.closing_sign, chosen.lip_side, chosen.pour_turn, chosen.pitch)
    ]
    assert len(same) == 1 and same[0].cost == pytest.approx(chosen.cost, abs=1e-9)
    # The search stops after the first turn offering a variant under GOOD_ENOUGH, else it tries
    # every turn: either way its choice is the cheapest of the turns it searched.
    last = POUR_TURNS.index(chosen.pour_turn) if chosen.cost < GOOD_ENOUGH else len(POUR_TURNS) - 1
    searched = [v.cost for v in variants if POUR_TURNS.index(v.pour_turn) <= last]
    assert min(searched) == pytest.approx(chosen.cost, abs=1e-9)


def test_bad_arguments_are_refused(m, tmp_path) -> None:
    with pytest.raises(SystemExit):
        m.main([])  # neither a recording nor evaluations
    path = tmp_path / "e.jsonl"
    record = {"task": "pour", "split": "test", "setting": "hard", "scale": 1.0, "object_id": 0}
    path.write_text(json.dumps(record | {"seed": 1, "success": True}) + "\n")
    with pytest.raises(SystemExit):
        m.main([str(path), "--tolerances", "-0.1"])
    with pytest.raises(SystemExit):
        m.main([str(path), "--tolerances", "a"])
    with pytest.raises(SystemExit):
        m.main([str(path), "--names", "a,b"])
    with pytest.raises(SystemExit):
        m.main(["--demos", str(tmp_path / "missing.zarr")])
