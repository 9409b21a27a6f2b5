"""Where a trained policy's rollouts go wrong: how close the hand gets to the grasp, and when it closes.

Run: ``.venv/bin/python benchmarks/rollout_diagnosis.py runs/pour50-keygen --split test --setting hard
--object-ids 0,1,2 --episodes 1 [--seed 1000] [--out benchmarks/results/NAME.json]``. Rolls out the
run's policy exactly as ``keygen eval`` does (same environment sizes, episode seeds
``SeedSequence([seed, object, k])``, one torch thread) and records, per episode, from the privileged
anchors the environment reports at every step (not seen by the policy):

- ``min_tcp_to_grasp_m``: the closest the tool centre came to the task's grasp anchor (pour and knife:
  ``handle_grasp``; stack: the circle of bowl A's rim through its ``rim_grasp``);
- ``first_close_step`` and ``tcp_to_grasp_at_close_m``: the first step whose gripper command drops
  below CLOSED_BELOW (0.04) after having been open, and the distance at that moment (where the
  policy decided to grasp); ``reopen_step``: the first later step whose command is open again (a
  drop after it is the policy letting go, not a slip);
- ``object_rise_m``: the most the grasp anchor rose above its start (did the object ever leave the table);
- pour only, where the pour went: ``tip_step``, the first step at which the task's ``mug_tilt_deg``
  exceeds TIP_DEG (90; the spheres start to leave), and at that step ``lip_to_box_cm``, the
  horizontal distance from the opening centre to the box's inner centre, and ``lip_in_box``, the same
  offset along the box's own x and y axes in units of its inner half extents (within [-1, 1] on both:
  over the opening); None when the mug never tipped that far; ``tcp_from_grasp_at_lift_cm``, where
  the tool centre holds the handle once the mug has risen LIFT_M: its offset from the handle's grasp
  anchor, [outward along the handle, sideways, up] (the first two horizontal, outward being from the
  opening's centre to the anchor); None when it never rose that far;
- the carry (every task; the steps at which the object is more than LIFT_M above its start, before
  the gripper reopens):
  ``carry_command_median``, the median gripper command, and ``carry_squeeze_n`` [median, min], the jaw
  squeeze the position-controlled gripper then exerts, from the command and the measured opening
  (``carry_squeeze``; the experts command 0 there); None where the object never rose;
- ``carry_pivot_deg`` [median, 90th percentile, max]: how far the object has turned in the hand since
  the carry's first step (the angle of its rotation relative to the tool frame); a slip that starts
  as a swing about the pinch shows here before the object falls (the maximum includes the fall);
- ``object_mass_kg`` and ``object_friction``: the manipulated object's mass and the median sliding
  friction of its collision geoms in this episode (after the environment's physics randomisation,
  which is off unless the environment is made with it);
- knife only, how the blade met the block after a lift (None while the knife never rose LIFT_M):
  ``slot_closest_cm``, the smallest horizontal distance from the blade tip to the slot's centre over the
  lifted steps, and at that step ``slot_yaw_err_deg``, the angle between the blade's width (edge
  direction) and the slot's long axis (0-90), ``blade_tilt_deg``, the blade's tilt from pointing
  straight down, and ``tip_above_block_cm``, the tip's height over the block's top (negative: in the
  slot or beside it); ``slot_width_cm`` for scale;
- the episode's success, failure reason and steps.

``--gripper-kp-scale S`` multiplies the gripper servo's stiffness in every episode (an intervention on
the simulated physics, to ask whether a firmer squeeze would keep a grip; the jaw force still saturates
at GRIP_FORCE); ``carry_squeeze_n`` then uses the scaled stiffness.

Prints a table and writes JSON. A diagnosis tool, not a benchmark of speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from keygen.evaluation.evaluate import load_policy_runner, read_run_info  # noqa: E402
from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env  # noqa: E402
from keygen.geometry.rotations import rotation_angle_between  # noqa: E402
from keygen.sim.robot import FINGER_MAX, GRIP_FORCE, GRIPPER_KP  # noqa: E402

GRASP_ANCHOR = {"pour": "handle_grasp", "knife": "handle_grasp", "stack": "rim_grasp"}


def _grasp_distance(task: str, tcp: np.ndarray, anchors: dict) -> float:
    """Distance from the tcp to the grasp target; for a bowl, to the rim circle through rim_grasp."""
    grasp = np.asarray(anchors[GRASP_ANCHOR[task]], float)
    if task != "stack":
        return float(np.linalg.norm(tcp - grasp))
    # A round bowl: any point of the rim circle at the anchor's height is as good as the anchor.
    centre = np.asarray(anchors["opening_center"], float)
    radius = float(np.linalg.norm((grasp - centre)[:2]))
    d = tcp - centre
    radial = np.hypot(d[0], d[1]) - radius
    return float(np.hypot(radial, d[2] - (grasp[2] - centre[2])))


TIP_DEG = 90.0


def lip_offset_from_box(anchors: dict) -> tuple[float, list[float]]:
    """The mug's opening centre's horizontal offset from the box's inner centre: distance in cm, and
    along the box's x, y axes in units of its inner half extents."""
    offset = np.asarray(anchors["opening_center"], float) - np.asarray(anchors["container_center"], float)
    x_axis = np.asarray(anchors["container_x_axis"], float)
    y_axis = np.cross([0.0, 0.0, 1.0], x_axis)
    half = np.asarray(anchors["container_half_extents"], float)
    in_box = [float(offset @ x_axis / half[0]), float(offset @ y_axis / half[1])]
    return float(100 * np.hypot(offset[0], offset[1])), in_box


LIFT_M = 0.03  # the object counts as lifted (the knife's slot approach, the mug's carry) past this rise


def grasp_offset_cm(tcp: np.ndarray, anchors: dict) -> list[float]:
    """The tcp's offset from a mug's handle grasp anchor in cm: [outward along the handle, sideways,
    up], outward being the horizontal direction from the opening's centre to the anchor."""
    grasp = np.asarray(anchors["handle_grasp"], float)
    out = (grasp - np.asarray(anchors["opening_center"], float))[:2]
    out = out / max(float(np.linalg.norm(out)), 1e-9)
    side = np.array([-out[1], out[0]])
    d = np.asarray(tcp, float) - grasp
    return [
        round(100 * float(d[:2] @ out), 2),
        round(100 * float(d[:2] @ side), 2),
        round(100 * float(d[2]), 2),
    ]


def blade_at_slot(anchors: dict) -> tuple[float, float, float, float]:
    """How the blade meets the slot, from the knife task's world anchors: the horizontal distance from
    the blade tip to the slot's centre (cm); the angle between the blade's width (its edge direction,
    which the expert lays along the slot) and the slot's long axis, horizontal parts only (deg, 0-90:
    edge and spine fit the slot alike); the blade's tilt from pointing straight down (deg); and the
    tip's height over the block top (cm)."""
    tip, base = np.asarray(anchors["blade_tip"], float), np.asarray(anchors["blade_base"], float)
    centre = np.asarray(anchors["slot_center_top"], float)
    edge = np.asarray(anchors["edge_direction"], float)[:2]
    axis = np.asarray(anchors["slot_axis"], float)[:2]
    cos_yaw = abs(float(edge @ axis)) / max(float(np.linalg.norm(edge) * np.linalg.norm(axis)), 1e-9)
    blade = tip - base
    cos_tilt = float(-blade[2]) / max(float(np.linalg.norm(blade)), 1e-9)
    return (
        float(100 * np.hypot(*(tip - centre)[:2])),
        float(np.degrees(np.arccos(min(1.0, cos_yaw)))),
        float(np.degrees(np.arccos(np.clip(cos_tilt, -1.0, 1.0)))),
        float(100 * (tip[2] - centre[2])),
    )


# A gripper command below this is a close: the experts close to 0 and approach open by at least 0.06
# (the pour expert's fitted opening through a narrow handle), so 0.5 would mistake a pour approach
# for a grasp.
CLOSED_BELOW = 0.04


def gripper_events(commands) -> tuple[int | None, int | None]:
    """(first close, first reopen after it): the first step whose command is below CLOSED_BELOW after
    an open one, and the first later step at or above it again; None where there is none."""
    close = reopen = None
    was_open = False
    for step, command in enumerate(commands):
        is_open = float(command) >= CLOSED_BELOW
        if close is None:
            if is_open:
                was_open = True
            elif was_open:
                close = step
        elif is_open:
            reopen = step
            break
    return close, reopen


def carry_squeeze(commands, openings, kp_scale: float = 1.0) -> np.ndarray:
    """Jaw squeeze (N) of the gripper per step from its command and measured opening fraction.

    The gripper is a position servo on the fingers' mean stroke (``keygen.sim.robot``): its tendon
    force is GRIPPER_KP * FINGER_MAX * (opening - command), saturating at 2 * GRIP_FORCE, and each jaw
    gets half; commands below 0 are clipped as the controller clips them. Closed on a handle (command
    0), it therefore squeezes in proportion to the handle's thickness: 35 N on a 7 mm handle, 28 N on
    5.6 mm; and a command above 0 takes its share off that. ``kp_scale``: the servo's stiffness over
    GRIPPER_KP (``scale_gripper_stiffness``)."""
    gap = np.asarray(openings, float) - np.clip(np.asarray(commands, float), 0.0, 1.0)
    return np.clip(kp_scale * GRIPPER_KP * FINGER_MAX * gap, 0.0, 2 * GRIP_FORCE) / 2


def scale_gripper_stiffness(model, handles, scale: float) -> None:
    """Multiply the gripper's position-servo stiffness (gain and the matching bias) by ``scale``."""
    act = model.actuator(handles.gripper_actuator).id
    model.actuator_gainprm[act, 0] *= scale
    model.actuator_biasprm[act, 1] *= scale


def object_in_hand(env) -> np.ndarray:
    """(3, 3) rotation of the task's manipulated object relative to the tool-centre frame."""
    body = env.task.objects[0].body_id
    tcp = env.model.site(env.scene.robot.tcp_site).id
    return env.data.site_xmat[tcp].reshape(3, 3).T @ env.data.xmat[body].reshape(3, 3)


def pivot_angles_deg(in_hand) -> np.ndarray:
    """Degrees each (3, 3) object-in-hand rotation has turned from the first."""
    in_hand = np.asarray(in_hand, float)
    return np.degrees(np.asarray(rotation_angle_between(in_hand[:1], in_hand), float).reshape(-1))


def object_physics(env) -> tuple[float, float]:
    """(mass in kg, median sliding friction of its collision geoms) of the task's manipulated object."""
    body = env.task.objects[0].body_id
    geoms = np.flatnonzero((env.model.geom_bodyid == body) & (env.model.geom_contype > 0))
    return float(env.model.body_mass[body]), float(np.median(env.model.geom_friction[geoms, 0]))


def diagnose_episode(env, policy, task: str, seed: int, gripper_kp_scale: float = 1.0) -> dict:
    obs, info = env.reset(seed=int(seed))
    if gripper_kp_scale != 1.0:  # the model is compiled anew at each reset
        scale_gripper_stiffness(env.model, env.scene.robot, gripper_kp_scale)
    mass, friction = object_physics(env)
    policy.reset(seed=int(seed))
    start_z = float(np.asarray(info["anchors"][GRASP_ANCHOR[task]])[2])
    closest, rise, steps = np.inf, 0.0, 0
    # carried: (step, command, opening after it, the object's rotation in the hand) while held up
    commands, dists, carried = [], [], []
    pour = {"tip_step": None, "lip_to_box_cm": None, "lip_in_box": None, "tcp_from_grasp_at_lift_cm": None}
    slot = dict.fromkeys(("slot_closest_cm", "slot_yaw_err_deg", "blade_tilt_deg", "tip_above_block_cm"))
    if task == "knife":  # the block's slot is the same all episode
        slot["slot_width_cm"] = round(100 * float(np.asarray(info["anchors"]["slot_width"]).ravel()[0]), 2)
    terminated = truncated = False
    while not (terminated or truncated):
        action = np.asarray(policy.act(obs), dtype=np.float64)  # (10,)
        tcp = np.asarray(obs["proprio"][:3], float)
        dist = _grasp_distance(task, tcp, info["anchors"])
        closest = min(closest, dist)
        commands.append(float(action[9]))
        dists.append(dist)
        obs, _, terminated, truncated, info = env.step(action)
        lift = float(np.asarray(info["anchors"][GRASP_ANCHOR[task]])[2]) - start_z
        rise = max(rise, lift)
        steps += 1
        if lift > LIFT_M:  # held up now (not merely once: a dropped object leaves the carry)
            carried.append((steps - 1, commands[-1], float(obs["proprio"][9]), object_in_hand(env)))
        if task == "knife" and rise > LIFT_M:
            dist, yaw_err, tilt, above = blade_at_slot(info["anchors"])
            if slot["slot_closest_cm"] is None or dist < slot["slot_closest_cm"]:
                slot.update(
                    slot_closest_cm=round(dist, 2),
                    slot_yaw_err_deg=round(yaw_err, 1),
                    blade_tilt_deg=round(tilt, 1),
                    tip_above_block_cm=round(above, 2),
                )
        if task == "pour" and pour["tcp_from_grasp_at_lift_cm"] is None and rise > LIFT_M:
            pour["tcp_from_grasp_at_lift_cm"] = grasp_offset_cm(obs["proprio"][:3], info["anchors"])
        if task == "pour" and pour["tip_step"] is None and info["metrics"]["mug_tilt_deg"] > TIP_DEG:
            dist, in_box = lip_offset_from_box(info["anchors"])
            pour |= {
                "tip_step": steps,
                "lip_to_box_cm": round(dist, 2),
                "lip_in_box": [round(v, 3) for v in in_box],
            }
    close_step, reopen_step = gripper_events(commands)
    close_dist = None if close_step is None else dists[close_step]
    if reopen_step is not None:  # the carry ends where the policy lets go
        carried = [c for c in carried if c[0] < reopen_step]
    carry = {"carry_command_median": None, "carry_squeeze_n": None, "carry_pivot_deg": None}
    if carried:
        _, held_commands, openings, in_hand = zip(*carried, strict=True)
        pivot = pivot_angles_deg(in_hand)
        squeeze = carry_squeeze(held_commands, openings, gripper_kp_scale)
        carry = {
            "carry_command_median": round(float(np.median(held_commands)), 4),
            "carry_squeeze_n": [round(float(np.median(squeeze)), 1), round(float(squeeze.min()), 1)],
            "carry_pivot_deg": [round(float(v), 1) for v in np.percentile(pivot, [50, 90, 100])],
        }
    return (
        {
            "success": bool(info["success"]),
            "failure": None if info["success"] else (info.get("failure") or ("timeout" if truncated else "")),
            "steps": steps,
            "min_tcp_to_grasp_m": round(float(closest), 4),
            "first_close_step": close_step,
            "tcp_to_grasp_at_close_m": None if close_dist is None else round(float(close_dist), 4),
            "reopen_step": reopen_step,
            "object_rise_m": round(rise, 4),
            # The size frame's scale as measured at the episode's first query (None without one):
            # one number for the uniform frame, (horizontal, horizontal, vertical) for the per-axis one.
            "size_scale": _size_scale(policy),
            "object_mass_kg": round(mass, 4),
            "object_friction": round(friction, 3),
        }
        | carry
        | (pour if task == "pour" else {})
        | (slot if task == "knife" else {})
    )


def _size_scale(policy) -> float | list[float] | None:
    frame = getattr(policy, "size_frame", None)
    if frame is None:
        return None
    scale = np.asarray(frame.scale, dtype=float)
    return round(float(scale), 4) if scale.ndim == 0 else [round(float(v), 4) for v in scale]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir")
    p.add_argument("--split", default="test", choices=["test", "train", "seen"])
    p.add_argument("--setting", default="hard", choices=["easy", "hard"])
    p.add_argument("--object-ids", default="0,1,2", help="comma-separated ids")
    p.add_argument("--episodes", type=int, default=1, help="episodes per object")
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument(
        "--size-normalize",
        nargs="?",
        const="uniform",
        default=None,
        choices=["uniform", "axes"],
        help="as keygen eval --size-normalize",
    )
    p.add_argument(
        "--gripper-kp-scale",
        type=float,
        default=1.0,
        help="multiply the gripper servo's stiffness (a physics intervention; see the module docstring)",
    )
    p.add_argument("--out", default=None, help="JSON path (default: print only)")
    args = p.parse_args(argv)
    if not args.gripper_kp_scale > 0:
        p.error(f"--gripper-kp-scale must be > 0, got {args.gripper_kp_scale}")
    torch.set_num_threads(1)
    info = read_run_info(args.run_dir)
    split = info.train_split if args.split == "seen" else args.split
    if args.split == "seen":
        ids = list(info.train_object_ids)
    else:
        ids = [int(i) for i in args.object_ids.split(",")]
    policy = load_policy_runner(args.run_dir, size_normalize=args.size_normalize)
    rows = []
    t0 = time.perf_counter()
    for oid in ids:
        env = make_env(EnvSpec(info.task, split, args.setting, 1.0, info.image_size, info.num_points), oid)
        for k in range(args.episodes):
            row = {"object_id": oid, "episode": k}
            row |= diagnose_episode(
                env, policy, info.task, episode_seed(args.seed, oid, k), args.gripper_kp_scale
            )
            rows.append(row)
            close = row["tcp_to_grasp_at_close_m"]
            print(
                f"object {oid:2d} ep {k}: {'success' if row['success'] else row['failure']:>14s}  "
                f"closest {100 * row['min_tcp_to_grasp_m']:5.1f} cm  first close at step "
                f"{row['first_close_step']} ({'-' if close is None else f'{100 * close:.1f} cm'})"
                + ("" if row["reopen_step"] is None else f", reopened at step {row['reopen_step']}")
                + "  "
                f"object rose {100 * row['object_rise_m']:.1f} cm"
                + ("" if row["size_scale"] is None else f"  size scale {row['size_scale']}")
                + (
                    f"  carried with command {row['carry_command_median']:.3f}, squeeze "
                    f"{row['carry_squeeze_n'][0]:.0f} N (min {row['carry_squeeze_n'][1]:.0f}), "
                    f"turned in the hand {row['carry_pivot_deg'][1]:.0f} deg (90th pct)"
                    if row["carry_command_median"] is not None
                    else ""
                )
                + (
                    f"  tipped at step {row['tip_step']}, lip {row['lip_to_box_cm']:.1f} cm off box centre"
                    if row.get("tip_step") is not None
                    else ""
                )
                + (
                    f"  blade tip {row['slot_closest_cm']:.1f} cm from the slot, "
                    f"width {row['slot_yaw_err_deg']:.0f} deg off its axis, "
                    f"tilt {row['blade_tilt_deg']:.0f} deg, "
                    f"{row['tip_above_block_cm']:.1f} cm over the block "
                    f"(slot {row['slot_width_cm']:.1f} cm wide)"
                    if row.get("slot_closest_cm") is not None
                    else ""
                ),
                flush=True,
            )
        env.close()
    report = {
        "run_dir": args.run_dir,
        "task": info.task,
        "policy": info.policy,
        "split": split,
        "setting": args.setting,
        "seed": args.seed,
        "size_normalize": args.size_normalize,
        "gripper_kp_scale": args.gripper_kp_scale,
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus",
        "seconds": round(time.perf_counter() - t0, 1),
        "episodes": rows,
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps({k: v for k, v in report.items() if k != "episodes"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
