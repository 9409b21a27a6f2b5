"""``keygen sim``: look at the environments (render an episode to a video)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from keygen.errors import InvalidParameterError


def register(sub: argparse._SubParsersAction) -> None:
    sim = sub.add_parser("sim", help="the MuJoCo benchmark environments")
    ssub = sim.add_subparsers(dest="sim_command", required=True)
    render = ssub.add_parser("render", help="render an episode with the four views tiled (mp4 or gif)")
    render.add_argument("--task", required=True, choices=["pour", "knife", "stack"])
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--out", required=True, type=Path, help="video file (.mp4 or .gif)")
    render.add_argument("--split", default="test", choices=["train", "test", "policy"])
    render.add_argument("--object-id", type=int, default=0)
    render.add_argument("--setting", default="easy", choices=["easy", "hard"])
    render.add_argument("--scale", type=float, default=1.0)
    render.add_argument("--randomize", action="store_true", help="turn on every domain randomisation")
    render.add_argument("--steps", type=int, default=40, help="control steps (10 Hz)")
    render.add_argument("--image-size", type=int, default=128)
    render.add_argument(
        "--actions",
        default="reach",
        choices=["reach", "random"],
        help="reach: move the open gripper above the object's grasp anchor and back; random: a random walk",
    )
    render.set_defaults(func=cmd_render)


def reach_targets(start: np.ndarray, anchor: np.ndarray, steps: int) -> np.ndarray:
    """A smooth out-and-back path of the tcp from its start to 8 cm above ``anchor`` (orientation kept)."""
    above = anchor + np.array([0.0, 0.0, 0.08])
    phase = 0.5 - 0.5 * np.cos(np.linspace(0, 2 * np.pi, steps))  # 0 -> 1 -> 0
    targets = np.repeat(start[None], steps, axis=0)
    targets[:, :3] = start[:3] + phase[:, None] * (above - start[:3])
    return targets


def random_targets(start: np.ndarray, rng: np.random.Generator, steps: int) -> np.ndarray:
    walk = np.cumsum(rng.normal(0.0, 0.01, (steps, 3)), axis=0)
    targets = np.repeat(start[None], steps, axis=0)
    targets[:, :3] = start[:3] + np.clip(walk, -0.12, 0.12)
    targets[:, 9] = (rng.uniform(size=steps) > 0.5).astype(float)
    return targets


def cmd_render(args: argparse.Namespace) -> int:
    import gymnasium as gym
    import imageio.v2 as imageio
    from tqdm import tqdm

    import keygen

    if args.out.suffix.lower() not in (".mp4", ".gif"):
        raise InvalidParameterError(f"--out must end in .mp4 or .gif, got {args.out.name!r}")
    if args.steps < 1:
        raise InvalidParameterError(f"--steps must be >= 1, got {args.steps}")
    env = gym.make(
        keygen.ENV_IDS[args.task],
        object_split=args.split,
        object_id=args.object_id,
        setting=args.setting,
        scale=args.scale,
        randomize=args.randomize,
        image_size=args.image_size,
        render_mode="rgb_array",
    ).unwrapped
    t0 = time.perf_counter()
    obs, info = env.reset(seed=args.seed)
    start = obs["proprio"].astype(float)
    if args.actions == "reach":
        name = {"pour": "handle_grasp", "knife": "handle_grasp", "stack": "rim_grasp"}[args.task]
        targets = reach_targets(start, info["anchors"][name], args.steps)
    else:
        targets = random_targets(start, np.random.default_rng(args.seed), args.steps)
    frames = [env.render()]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for target in tqdm(targets, desc=f"render {args.task}", unit="step"):
        obs, _, terminated, truncated, info = env.step(target)
        frames.append(env.render())
        if terminated or truncated:
            break
    env.close()
    if args.out.suffix.lower() == ".gif":
        imageio.mimsave(args.out, frames, duration=0.1, loop=0)
    else:
        imageio.mimsave(args.out, frames, fps=10, macro_block_size=1)
    print(
        json.dumps(
            {
                "out": str(args.out),
                "frames": len(frames),
                "success": info["success"],
                "failure": info["failure"],
                "seconds": round(time.perf_counter() - t0, 2),
            }
        )
    )
    return 0
