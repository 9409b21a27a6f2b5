"""The gripper holds a pinched mug handle with a steady squeeze under a constant command.

Regression for a servo/finger/contact limit cycle (finger drive armature 0.1 kg): with the command
held at "closed", the squeeze swung between 0 and ~70 N at ~11 Hz and every zero let the handle slide
along the pads until the mug fell out. The case is the first one found: test mug 1, hard, episode 0 of
an evaluation seeded 1000, the pinch expert carrying the mug; the arm is then frozen and the physics
runs on for one second.
"""

from __future__ import annotations

import mujoco
import numpy as np

from keygen.evaluation.rollout import EnvSpec, episode_seed, make_env
from keygen.expert.runner import make_expert

CARRY_STEP = 75  # the mug is lifted and carried; with the old drive it fell out here


def _pad_force(model, data, pad: int, body: int) -> float:
    total, f6 = 0.0, np.zeros(6)
    for i in range(data.ncon):
        c = data.contact[i]
        if pad in (c.geom1, c.geom2) and body in (model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]):
            mujoco.mj_contactForce(model, data, i, f6)
            total += f6[0]
    return total


def test_pinched_handle_is_squeezed_steadily_and_does_not_walk_out() -> None:
    env = make_env(EnvSpec("pour", "test", "hard", image_size=32, num_points=64), 1)
    obs, info = env.reset(seed=episode_seed(1000, 1, 0))
    expert = make_expert("pour", grasp="pinch")
    expert.reset(env, obs, info)
    for _ in range(CARRY_STEP):
        obs, _, terminated, truncated, info = env.step(expert.act(obs, info))
        assert not (terminated or truncated)
    model, data, mug = env.model, env.data, env.task.manipulated.body_id
    pads = [model.geom(f"robot/pad_{side}").id for side in ("left", "right")]
    assert all(_pad_force(model, data, p, mug) > 1.0 for p in pads), "the handle is not pinched"

    start = data.geom_xmat[pads[0]].reshape(3, 3).T @ (data.xpos[mug] - data.geom_xpos[pads[0]])
    forces = []
    for _ in range(500):  # 1 s, every actuator's command held
        mujoco.mj_step(model, data)
        forces.append([_pad_force(model, data, p, mug) for p in pads])
    forces = np.array(forces)
    end = data.geom_xmat[pads[0]].reshape(3, 3).T @ (data.xpos[mug] - data.geom_xpos[pads[0]])
    assert forces.min() > 20.0  # never let go (the limit cycle reached 0 every ~90 ms)
    assert forces.std(axis=0).max() < 5.0  # steady, not swinging between 0 and 70 N
    assert np.linalg.norm(end - start) < 0.002  # the mug stays put in the pads' frame
    env.close()
