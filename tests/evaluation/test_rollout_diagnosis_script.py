"""benchmarks/rollout_diagnosis.py: the pour fields (where the mug's opening is relative to the box
when it tips), the knife fields (how the blade meets the slot) and the gripper's close and reopen on
hand-built inputs whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def m(load_benchmark_script):
    return load_benchmark_script("rollout_diagnosis")


def _anchors(opening: np.ndarray, box_yaw: float) -> dict:
    return {
        "opening_center": opening,
        "container_center": np.array([0.5, -0.2, 0.06]),
        "container_x_axis": np.array([np.cos(box_yaw), np.sin(box_yaw), 0.0]),
        "container_half_extents": np.array([0.08, 0.06, 0.03]),
    }


def test_opening_over_the_box_centre_sits_at_the_origin(m) -> None:
    dist, in_box = m.lip_offset_from_box(_anchors(np.array([0.5, -0.2, 0.2]), 0.3))
    assert dist == pytest.approx(0.0, abs=1e-9) and in_box == pytest.approx([0.0, 0.0], abs=1e-9)


def test_offset_is_read_in_the_box_frame_in_half_extents(m) -> None:
    # Box turned 90 degrees: its x axis is world +y, its y axis world -x.
    opening = np.array([0.5 - 0.03, -0.2 + 0.04, 0.2])  # 4 cm along the box's x, 3 cm along its y
    dist, in_box = m.lip_offset_from_box(_anchors(opening, np.pi / 2))
    assert dist == pytest.approx(5.0)
    assert in_box == pytest.approx([0.04 / 0.08, 0.03 / 0.06])


def test_size_scale_reads_the_runners_measured_frame(m) -> None:
    class Frame:
        def __init__(self, scale):
            self.scale = scale

    class Runner:
        size_frame = None

    runner = Runner()
    assert m._size_scale(runner) is None  # no size frame measured (or none asked for)
    runner.size_frame = Frame(1.23456)
    assert m._size_scale(runner) == 1.2346
    runner.size_frame = Frame(np.array([1.5, 1.5, 2.25]))
    assert m._size_scale(runner) == [1.5, 1.5, 2.25]
    assert m._size_scale(object()) is None  # a runner without the attribute


def test_blade_at_slot_measures_offset_width_yaw_tilt_and_height(m) -> None:
    slot = {"slot_center_top": np.array([0.6, 0.1, 0.12]), "slot_axis": np.array([0.0, 1.0, 0.0])}

    def blade(base, tip, edge) -> dict:
        return slot | {
            "blade_base": np.array(base),
            "blade_tip": np.array(tip),
            "edge_direction": np.array(edge),
        }

    # Pointing straight down, width along the slot, tip 3 cm to the side of the centre, 2 cm above the top.
    assert m.blade_at_slot(blade([0.63, 0.1, 0.3], [0.63, 0.1, 0.14], [0, 1, 0])) == pytest.approx(
        (3.0, 0.0, 0.0, 2.0), abs=1e-9
    )
    # Width reversed (spine first) fits as well; turned 45 degrees about the vertical, 45; across, 90.
    assert m.blade_at_slot(blade([0.6, 0.1, 0.3], [0.6, 0.1, 0.11], [0, -1, 0]))[:2] == pytest.approx((0, 0))
    assert m.blade_at_slot(blade([0.6, 0.1, 0.3], [0.6, 0.1, 0.2], [1, 1, 0]))[1] == pytest.approx(45.0)
    assert m.blade_at_slot(blade([0.6, 0.1, 0.3], [0.6, 0.1, 0.2], [1, 0, 0]))[1] == pytest.approx(90.0)
    # Lying flat (the blade horizontal) is 90 degrees of tilt; pointing up, 180.
    assert m.blade_at_slot(blade([0.5, 0.1, 0.2], [0.6, 0.1, 0.2], [0, 1, 0]))[2] == pytest.approx(90.0)
    assert m.blade_at_slot(blade([0.6, 0.1, 0.1], [0.6, 0.1, 0.2], [0, 1, 0]))[2] == pytest.approx(180.0)


def test_gripper_events_find_the_close_after_an_open_and_the_reopen_after_it(m) -> None:
    # Starts closed (not a grasp), opens, closes at step 4, opens again at step 7.
    commands = [0.0, 0.0, 0.08, 0.06, 0.01, 0.0, 0.039, 0.04, 0.0]
    assert m.gripper_events(commands) == (4, 7)
    assert m.gripper_events([0.08, 0.08, 0.0, 0.0]) == (2, None)  # holds to the end
    assert m.gripper_events([0.0, 0.0, 0.0]) == (None, None)  # never open, so never a grasp
    assert m.gripper_events([]) == (None, None)


def test_grasp_offset_reads_outward_sideways_and_up_from_the_handle(m) -> None:
    # Handle along -y of the opening's centre; the tcp 1 cm further out, 0.5 cm to the side, 2 cm up.
    anchors = {"opening_center": np.array([0.4, 0.1, 0.12]), "handle_grasp": np.array([0.4, 0.03, 0.08])}
    out, side = np.array([0.0, -1.0]), np.array([1.0, 0.0])  # side: out turned +90 degrees about z
    tcp = anchors["handle_grasp"] + np.r_[0.01 * out + 0.005 * side, 0.02]
    np.testing.assert_allclose(m.grasp_offset_cm(tcp, anchors), [1.0, 0.5, 2.0], atol=1e-9)
    np.testing.assert_allclose(
        m.grasp_offset_cm(anchors["handle_grasp"], anchors), [0.0, 0.0, 0.0], atol=1e-12
    )


def test_carry_squeeze_follows_the_servo_and_saturates(m) -> None:
    from keygen.sim.robot import FINGER_MAX, GRIP_FORCE, GRIPPER_KP

    # Fingers stopped by a 7 mm handle: each jaw 3.5 mm out, i.e. an opening fraction of 0.0875.
    opening = 0.0035 / FINGER_MAX
    full = GRIPPER_KP * 0.0035 / 2  # commanded closed: the whole 3.5 mm of stroke error
    squeeze = m.carry_squeeze([0.0, -0.2, 0.03, opening, 0.5], [opening] * 5)
    assert squeeze[0] == pytest.approx(full)
    assert squeeze[1] == pytest.approx(full)  # below 0 is clipped, as the controller does
    assert squeeze[2] == pytest.approx(full * (1 - 0.03 / opening))  # a third lost on this handle
    thinner = m.carry_squeeze([0.0], [0.0028 / FINGER_MAX])[0]  # a 5.6 mm handle squeezed less
    assert thinner == pytest.approx(full * 0.8)
    assert squeeze[3] == pytest.approx(0.0) and squeeze[4] == pytest.approx(0.0)  # no push outward
    assert m.carry_squeeze([0.0], [1.0])[0] == pytest.approx(GRIP_FORCE)  # saturated


def test_stiffer_gripper_scales_the_squeeze_and_the_servo(m) -> None:
    from types import SimpleNamespace

    from keygen.sim.robot import FINGER_MAX, GRIP_FORCE, GRIPPER_KP, build_robot_spec, robot_handles

    opening = 0.0035 / FINGER_MAX
    assert m.carry_squeeze([0.0], [opening], 2.0)[0] == pytest.approx(GRIPPER_KP * 0.0035)  # doubled
    assert m.carry_squeeze([0.0], [opening], 3.0)[0] == pytest.approx(GRIP_FORCE)  # still saturates

    model = build_robot_spec().compile()
    handles = robot_handles()
    act = model.actuator(handles.gripper_actuator).id
    m.scale_gripper_stiffness(model, handles, 2.0)
    assert model.actuator_gainprm[act, 0] == pytest.approx(2 * GRIPPER_KP)
    assert model.actuator_biasprm[act, 1] == pytest.approx(-2 * GRIPPER_KP)  # position servo stays at 0 error

    # object_physics reads the manipulated object's (the task's first object's) mass and collision friction.
    fake_model = SimpleNamespace(
        geom_bodyid=np.array([0, 3, 3, 3]),
        geom_contype=np.array([1, 1, 0, 1]),  # the third geom is visual only
        geom_friction=np.array([[9.0, 0, 0], [0.5, 0, 0], [9.0, 0, 0], [0.7, 0, 0]]),
        body_mass=np.array([0.0, 0.0, 0.0, 0.31]),
    )
    env = SimpleNamespace(model=fake_model, task=SimpleNamespace(objects=[SimpleNamespace(body_id=3)]))
    assert m.object_physics(env) == pytest.approx((0.31, 0.6))


def test_pivot_angles_measure_the_turn_in_the_hand_from_the_first_step(m) -> None:
    def rz(deg):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    start = rz(30)  # whatever the object's rotation in the hand at the carry's start, angles count from it
    angles = m.pivot_angles_deg([start, start @ rz(5), start @ rz(-20), start @ rz(179)])
    assert angles == pytest.approx([0.0, 5.0, 20.0, 179.0], abs=1e-6)
