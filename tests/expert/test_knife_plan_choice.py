"""The knife planner's two ways of choosing among its candidates, on previewed costs set by hand.

The geometry and the controller preview are replaced by stand-ins that tag each candidate's target
sequence with its hand, pitch and route, so the costs the planner sees are exactly the ones given.
"""

import numpy as np
import pytest

from keygen.errors import InvalidParameterError
from keygen.expert import knife_plan
from keygen.expert.knife import KnifeExpert


class _Result:
    def __init__(self, cost: float) -> None:
        self._cost, self.q = cost, [np.zeros(7)]

    def cost(self) -> float:
        return self._cost


class _TaggedPreview:
    """Grasp cost by (hand, pitched); the transport's by route (default 0)."""

    def __init__(self, grasp_costs: dict, route_costs: dict | None = None) -> None:
        self.grasp_costs, self.route_costs = grasp_costs, route_costs or {}

    def rollout(self, q0, actions, checker, checkpoints):
        tag = actions[0]
        if tag[0] == "grasp":
            return _Result(self.grasp_costs[tag[1], tag[2] != 0.0])
        return _Result(self.route_costs.get(tag[1], 0.0))


@pytest.fixture
def planner_factory(monkeypatch):
    monkeypatch.setattr(
        knife_plan,
        "grasp_targets",
        lambda anchors, hand, p, r, pitch=0.0: ([("grasp", hand, pitch)], np.zeros(3), np.eye(3)),
    )
    monkeypatch.setattr(knife_plan, "insert_pose", lambda *args, **kwargs: None)
    monkeypatch.setattr(knife_plan, "insertion_targets", lambda hover, stages: [])
    monkeypatch.setattr(knife_plan, "insertion_pitch", lambda anchors, hand, approach, offset, size: size)
    monkeypatch.setattr(knife_plan, "insert_approach", lambda anchors: np.array([0.0, 1.0, 0.0]))
    anchors = {
        "slot_axis": np.array([1.0, 0.0, 0.0]),
        "slot_center_top": np.array([0.5, 0.2, 0.1]),
        "blade_axis": np.array([0.0, 1.0, 0.0]),
        "slot_depth": np.array([0.05]),
    }

    def make(choice: str, grasp_costs: dict, route_costs: dict | None = None):
        planner = knife_plan.KnifePlanner(None, _TaggedPreview(grasp_costs, route_costs), None, [], choice)
        planner._transport = lambda route, q, lifted, down, pre: [("after", route)]
        planner.choose_here = lambda: planner.choose(anchors, 0.0, np.zeros(7), (np.zeros(3), np.eye(3)))
        return planner

    return make


def _costs(hand0: float, hand1: float, pitched_extra: float = 0.0) -> dict:
    return {(0, False): hand0, (0, True): hand0 + pitched_extra, (1, False): hand1, (1, True): hand1}


def test_first_keeps_the_preferred_hand_where_it_is_good_enough(planner_factory):
    # Hand 0 is feasible but previews 0.05 worse than hand 1: least cost switches hands, first does not.
    costs = _costs(hand0=0.06, hand1=0.0)
    assert planner_factory("cost", costs).choose_here().hand == 1
    plan = planner_factory("first", costs).choose_here()
    assert (plan.hand, plan.pitch, plan.route) == (0, 0.0, "geodesic")
    assert plan.approach @ np.array([0.0, 1.0, 0.0]) > 0  # the preferred insertion side


def test_first_takes_upright_before_pitched_and_switches_only_when_markedly_worse(planner_factory):
    # Upright hand 0 previews within the tolerance of a cheaper pitched grasp: upright is kept.
    plan = planner_factory("first", _costs(hand0=0.05, hand1=0.2, pitched_extra=-0.05)).choose_here()
    assert (plan.hand, plan.pitch) == (0, 0.0)
    # Hand 0 previews worse than hand 1 by more than the tolerance: the next family in the order.
    plan = planner_factory("first", _costs(hand0=knife_plan.FIRST_TOLERANCE + 0.05, hand1=0.0)).choose_here()
    assert (plan.hand, plan.pitch) == (1, 0.0)
    plan = planner_factory("first", _costs(hand0=2.0, hand1=0.5)).choose_here()
    assert (plan.hand, plan.pitch) == (1, 0.0)


def test_first_previews_every_candidate_and_routes_come_after_the_grasp_family(planner_factory):
    costs = _costs(hand0=0.9, hand1=0.4)
    routes = {"geodesic": 0.5, "yaw_first_other": 0.3}
    planner = planner_factory("first", costs, routes)
    plan = planner.choose_here()
    # Only hand 1 by the second route is within the tolerance (0.7 against 0.9 and more).
    assert (plan.hand, plan.route, plan.pitch) == (1, "yaw_first_other", 0.0)
    assert plan.approach @ np.array([0.0, 1.0, 0.0]) > 0
    # 2 hands x 2 sides x 3 pitches x the 2 tcp routes; the joint-space fallback is not needed.
    assert len(planner.scored) == 24
    assert min(c for *_, c in planner.scored) == pytest.approx(0.7)


def test_unknown_plan_choice_is_refused():
    with pytest.raises(InvalidParameterError, match="plan choice"):
        knife_plan.KnifePlanner(None, None, None, [], choice="random")
    with pytest.raises(InvalidParameterError, match="plan_choice"):
        KnifeExpert(plan_choice="random")
