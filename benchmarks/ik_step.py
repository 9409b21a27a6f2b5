"""Cost of one differential-IK step: mink.solve_ik against keygen.sim.ik_step, on one core.

Run: ``.venv/bin/python benchmarks/ik_step.py [--configs 200] [--repeats 5]``.
Both solve the same QPs (random arm configurations, near and far targets, so the joint position and
velocity bounds are sometimes active); the table gives the median microseconds per solve over
``--repeats`` passes, the largest difference between their velocities, and the cost of a
controller update and of a 40-target route preview (the knife expert's planning unit) with either
path. Writes ``benchmarks/results/ik_step.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import mink  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from keygen.expert.preview import ControllerPreview  # noqa: E402
from keygen.geometry.rotations import matrix_to_rot6d  # noqa: E402
from keygen.sim import robot  # noqa: E402
from keygen.sim.controller import EndEffectorController  # noqa: E402


def _problems(ctrl: EndEffectorController, n: int, rng: np.random.Generator) -> list:
    lower, upper = np.array(robot.JOINT_LOWER), np.array(robot.JOINT_UPPER)
    site = ctrl._tcp_task.frame_name
    out = []
    for k in range(n):
        q = ctrl._ik_model.qpos0.copy()
        q[ctrl._ik_arm_qadr] = (
            rng.uniform(lower, upper) if k % 2 else np.array(robot.HOME_QPOS) + rng.normal(0, 0.05, 7)
        )
        ctrl._configuration.update(q)
        data = ctrl._configuration.data
        position = data.site(site).xpos + rng.normal(0, 0.002 if k % 2 == 0 else 0.2, 3)
        rotation = data.site(site).xmat.reshape(3, 3)
        out.append((q, np.concatenate([position, matrix_to_rot6d(rotation), [1.0]])))
    return out


def _per_call_us(fn, problems, ctrl, repeats: int) -> float:
    passes = []
    for _ in range(repeats):
        t = 0.0
        for q, target in problems:
            ctrl._configuration.update(q)
            ctrl.set_target(target)
            t0 = time.perf_counter()
            fn()
            t += time.perf_counter() - t0
        passes.append(t / len(problems) * 1e6)
    return statistics.median(passes)


def _route(preview: ControllerPreview, n: int) -> tuple[np.ndarray, np.ndarray]:
    q0 = np.array(robot.HOME_QPOS)
    preview.data.qpos[preview._qadr] = q0
    mujoco.mj_kinematics(preview.model, preview.data)
    start = preview.data.site_xpos[preview._site].copy()
    rotation = preview.data.site_xmat[preview._site].reshape(3, 3)
    targets = [
        np.concatenate([start + f * np.array([0.1, -0.15, -0.2]), matrix_to_rot6d(rotation), [1.0]])
        for f in np.linspace(0, 1, n)
    ]
    return q0, np.array(targets)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--configs", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "ik_step.json")
    args = parser.parse_args()

    spec = robot.recommended_options(mujoco.MjSpec())
    handles = robot.add_robot(spec)
    ctrl = EndEffectorController(spec.compile(), handles)
    problems = _problems(ctrl, args.configs, np.random.default_rng(0))
    tasks = [ctrl._tcp_task, ctrl._posture_task]
    dt = ctrl._ik_step.dt

    def mink_solve():
        return mink.solve_ik(ctrl._configuration, tasks, dt, "daqp", limits=ctrl._limits)

    worst = 0.0
    for q, target in problems:
        ctrl._configuration.update(q)
        ctrl.set_target(target)
        worst = max(worst, float(np.max(np.abs(ctrl._ik_step.solve() - mink_solve()))))
    rows = {
        "mink_solve_ik_us": _per_call_us(mink_solve, problems, ctrl, args.repeats),
        "ik_step_us": _per_call_us(ctrl._ik_step.solve, problems, ctrl, args.repeats),
        "max_abs_velocity_difference": worst,
    }

    preview = ControllerPreview(handles)
    q0, targets = _route(preview, 40)
    fast_step = preview.controller._ik_step
    for name, step in (("route_preview_mink_ms", None), ("route_preview_ik_step_ms", fast_step)):
        preview.controller._ik_step = step  # None: the controller falls back to mink.solve_ik
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            preview.rollout(q0, targets)
            times.append((time.perf_counter() - t0) * 1000)
        rows[name] = statistics.median(times)
    preview.controller._ik_step = fast_step

    print(f"one core, {args.configs} QPs x {args.repeats} passes (medians)")
    print("| path | per IK solve (us) | 40-target preview (ms) |")
    print("|---|---|---|")
    print(f"| mink.solve_ik | {rows['mink_solve_ik_us']:.1f} | {rows['route_preview_mink_ms']:.1f} |")
    print(f"| DifferentialIKStep | {rows['ik_step_us']:.1f} | {rows['route_preview_ik_step_ms']:.1f} |")
    print(f"largest |velocity difference|: {rows['max_abs_velocity_difference']:.3g} rad/s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.processor() or platform.machine(), "cpus_used": 1}
    args.out.write_text(json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
