"""The end-to-end benchmark: demonstrations -> keypoints -> policies -> evaluation, with stage reuse.

Layout under ``out``::

    demos/<task>/                 stage.json, demos.zarr
    keypoints/<category>/         stage.json, run/        (only for policies that use keypoints)
    policies/<task>/<policy>/     stage.json, run/
    eval/<task>/<policy>/<split>_<setting>/   stage.json, results.jsonl, summary.json

Every stage writes ``stage.json`` with a fingerprint of its inputs: the preset fields it reads plus the
fingerprints of the stages it reads from. A rerun skips a stage whose fingerprint matches and whose
outputs are complete, resumes one whose fingerprint matches but which did not finish (demonstrations,
training and evaluation all resume), and clears and reruns one whose inputs changed; since fingerprints
chain, everything after a changed stage reruns too. Objects need no stage: instances are pure functions
of (category, split, index, seed) and are built on demand.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from keygen.atomic import atomic_write_json
from keygen.errors import InvalidParameterError, KeyGenError
from keygen.sim import PHYSICS_VERSION

TASKS = ("pour", "knife", "stack")
TASK_CATEGORY = {"pour": "mug", "knife": "knife", "stack": "bowl"}
# Policy names by what they need (the registry, keygen.policies.config, is the source; a test keeps these
# equal to it without this module importing torch): keypoints, and a heading for the yaw frame.
KEYPOINT_POLICIES = ("keygen", "keygen_scene", "keygen_yaw")
YAW_FRAME_POLICIES = ("keygen_yaw",)
# Tasks whose manipulated object has a heading. A bowl is round: its keypoints fix no yaw, and a yaw
# frame fitted to them would only turn the scene at random, so yaw-frame policies skip stacking
# (training refuses them there; keygen.policies.config.HEADING_TASKS is the source).
HEADING_TASKS = ("pour", "knife")
STAGE_FILE = "stage.json"


class PipelineError(KeyGenError):
    """A benchmark stage cannot run or did not produce what it should."""


@dataclass(frozen=True)
class BenchmarkPreset:
    """Everything that fixes a benchmark run; validated on construction."""

    name: str
    demos: int  # demonstrations per task, on the training instance(s)
    image_size: int
    num_points: int
    keypoint_preset: str  # KeypointTrainConfig.preset name
    policy_preset: str  # TrainConfig.from_preset name
    unseen_ids: tuple[int, ...]  # test-split instances
    episodes_per_object: int
    demo_setting: str = "hard"
    demo_split: str = "policy"
    demo_object_ids: tuple[int, ...] = (0,)  # the seen instance(s)
    settings: tuple[str, ...] = ("easy", "hard")
    seed: int = 0  # demonstrations and training
    eval_seed: int = 1000
    workers: int = 2
    videos: int = 0  # per evaluation cell
    keypoint_overrides: dict[str, Any] = field(default_factory=dict)
    policy_overrides: dict[str, Any] = field(default_factory=dict)
    eval_max_steps: int | None = None
    num_inference_steps: int | None = None
    # Per task, keyword arguments of the recording expert (keygen.expert.runner.make_expert). Pouring
    # is recorded with the outside pinch of the handle on every mug: policies trained on the
    # finger-through grasp, which clears the training mug by 0.13 mm, ended 46-54 of 60 unseen
    # episodes with a finger on the body; on pinch recordings 1-16 (docs/benchmark.md, pouring).
    expert_options: dict[str, dict[str, Any]] = field(default_factory=lambda: {"pour": {"grasp": "pinch"}})

    def __post_init__(self) -> None:
        from keygen.objects.splits import SPLIT_SIZES

        for name in ("demos", "image_size", "num_points", "episodes_per_object", "workers"):
            if getattr(self, name) < 1:
                raise InvalidParameterError(f"preset {name} must be >= 1, got {getattr(self, name)}")
        if not set(self.settings) <= {"easy", "hard"} or not self.settings:
            raise InvalidParameterError(f"settings must be a non-empty subset of easy, hard: {self.settings}")
        if self.demo_setting not in ("easy", "hard"):
            raise InvalidParameterError(f"demo_setting must be easy or hard, got {self.demo_setting!r}")
        if not self.unseen_ids or not all(0 <= i < SPLIT_SIZES["test"] for i in self.unseen_ids):
            raise InvalidParameterError(
                f"unseen_ids must be test-split ids in [0, {SPLIT_SIZES['test']}), got {self.unseen_ids}"
            )
        if not self.demo_object_ids or not all(
            0 <= i < SPLIT_SIZES[self.demo_split] for i in self.demo_object_ids
        ):
            raise InvalidParameterError(
                f"demo_object_ids out of the {self.demo_split} split: {self.demo_object_ids}"
            )
        if self.videos < 0:
            raise InvalidParameterError(f"videos must be >= 0, got {self.videos}")
        unknown = sorted(set(self.expert_options) - set(TASK_CATEGORY))
        if unknown:
            raise InvalidParameterError(f"expert_options names unknown tasks {unknown}")

    def with_overrides(self, **overrides: Any) -> BenchmarkPreset:
        """A copy with the given fields changed (``None`` values are ignored: CLI flags left unset)."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise InvalidParameterError(f"unknown preset fields {unknown}; known: {sorted(known)}")
        return replace(self, **{k: v for k, v in overrides.items() if v is not None})


PRESETS: dict[str, BenchmarkPreset] = {
    # The paper's protocol: one training instance, 100 demonstrations, 12 unseen x 20 rollouts.
    "paper": BenchmarkPreset(
        name="paper",
        demos=100,
        image_size=128,
        num_points=1024,
        keypoint_preset="default",
        policy_preset="default",
        unseen_ids=tuple(range(12)),
        episodes_per_object=20,
    ),
    # A smoke test of the whole pipeline on 2 cores: its numbers are not a result.
    "quick": BenchmarkPreset(
        name="quick",
        demos=8,
        image_size=64,
        num_points=512,
        keypoint_preset="quick",
        policy_preset="quick",
        unseen_ids=(0, 1),
        episodes_per_object=1,
        # Cut schedules: three detectors, six policies and 48 rollouts must fit in ~15 minutes on
        # 2 cores (make demo). Every stage runs for real; the numbers only show that they connect.
        keypoint_overrides={"canon_steps": 80, "detector_steps": 80},
        policy_overrides={"steps": 150},
    ),
}


def get_preset(name: str, **overrides: Any) -> BenchmarkPreset:
    if name not in PRESETS:
        raise InvalidParameterError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
    return PRESETS[name].with_overrides(**overrides)


def fingerprint(inputs: dict[str, Any]) -> str:
    """A short stable hash of JSON-able stage inputs."""
    text = json.dumps(inputs, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)  # stdout is for the table and the final JSON


def run_stage(
    name: str,
    directory: Path,
    inputs: dict[str, Any],
    run: Callable[[], dict[str, Any]],
    complete: Callable[[dict[str, Any]], bool] = lambda outputs: True,
) -> dict[str, Any]:
    """Run a stage, or reuse its recorded outputs when its fingerprint matches and they are complete.

    Returns the stage record: name, fingerprint, inputs, outputs, status, seconds, reused, resumed.
    ``resumed`` marks a stage that an earlier invocation started and did not finish: its ``seconds``
    count this invocation only (a killed process records no time).
    """
    directory = Path(directory)
    record_path = directory / STAGE_FILE
    fp = fingerprint(inputs)
    resumed = False
    if record_path.exists():
        old = json.loads(record_path.read_text())
        if old.get("fingerprint") == fp and old.get("status") == "done" and complete(old.get("outputs", {})):
            _log(f"[benchmark] {name}: reused ({fp})")
            return old | {"reused": True}
        if old.get("fingerprint") != fp:
            _log(f"[benchmark] {name}: inputs changed ({old.get('fingerprint')} -> {fp}); rerunning")
            shutil.rmtree(directory)
        else:  # same inputs but unfinished: keep the partial outputs; the stage resumes from them
            resumed = True
    elif directory.exists() and any(directory.iterdir()):
        raise PipelineError(
            f"{directory} holds files but no {STAGE_FILE}: not written by `keygen benchmark`; "
            "choose another --out or remove the folder"
        )
    directory.mkdir(parents=True, exist_ok=True)
    record = {"name": name, "fingerprint": fp, "inputs": inputs, "status": "running", "outputs": {}}
    record["resumed"] = resumed
    record_path.write_text(json.dumps(record, indent=1, default=str))
    _log(f"[benchmark] {name}: {'resuming' if resumed else 'running'} ({fp})")
    t0 = time.perf_counter()
    outputs = run()
    record |= {"status": "done", "outputs": outputs, "seconds": round(time.perf_counter() - t0, 1)}
    atomic_write_json(record_path, record, indent=1)  # a crash leaves the "running" record, never a torn one
    return record | {"reused": False}


@dataclass
class StageFunctions:
    """What each stage does; the defaults run the real thing, tests inject fakes of the same shape."""

    demos: Callable[..., dict[str, Any]]  # (task, preset, path, progress) -> {"path", "episodes"}
    keypoints: Callable[..., dict[str, Any]]  # (category, preset, out_dir, progress) -> {"run_dir"}
    policy: Callable[..., dict[str, Any]]  # (task, policy, preset, dataset, keypoints, out_dir, progress)
    evaluate: Callable[..., dict[str, Any]]  # (run_dir, split, setting, object_ids, preset, jsonl, progress)


def default_stage_functions() -> StageFunctions:
    from keygen.evaluation import stages

    return StageFunctions(
        stages.record_demos, stages.train_keypoints, stages.train_policy, stages.evaluate_cell
    )


def _exists(key: str) -> Callable[[dict[str, Any]], bool]:
    return lambda outputs: key in outputs and Path(outputs[key]).exists()


def run_benchmark(
    preset: BenchmarkPreset,
    out: str | Path,
    tasks: tuple[str, ...] = TASKS,
    policies: tuple[str, ...] = ("keygen", "dp3"),
    functions: StageFunctions | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run (or reuse) every stage; returns {"preset", "results": [...], "stages": [...], "seconds"}."""
    unknown = sorted(set(tasks) - set(TASKS))
    if unknown or not tasks:
        raise InvalidParameterError(f"tasks must be a non-empty subset of {TASKS}, got {list(tasks)}")
    if not policies:
        raise InvalidParameterError("policies must name at least one policy")
    fns = functions or default_stage_functions()
    out = Path(out)
    t0 = time.perf_counter()
    stages: list[dict[str, Any]] = []
    results: list[dict[str, Any]] = []
    keypoint_records: dict[str, dict[str, Any]] = {}
    for task in tasks:
        demo_inputs = {
            "stage": "demos",
            "task": task,
            "split": preset.demo_split,
            "object_ids": list(preset.demo_object_ids),
            "setting": preset.demo_setting,
            "episodes": preset.demos,
            "seed": preset.seed,
            "image_size": preset.image_size,
            "num_points": preset.num_points,
            # Demonstrations recorded under another physics revision are recorded again, and with
            # them every later stage (their inputs hold this stage's fingerprint).
            "physics": PHYSICS_VERSION,
        }
        if preset.expert_options.get(task):  # absent when empty: older stages keep their fingerprint
            demo_inputs["expert_options"] = preset.expert_options[task]
        demo_dir = out / "demos" / task
        demos = run_stage(
            f"demos/{task}",
            demo_dir,
            demo_inputs,
            lambda task=task, d=demo_dir: fns.demos(task, preset, d / "demos.zarr", progress),
            lambda o: _exists("path")(o) and o.get("episodes", 0) >= preset.demos,
        )
        stages.append(demos)
        category = TASK_CATEGORY[task]
        if any(p in KEYPOINT_POLICIES for p in policies) and category not in keypoint_records:
            kp_inputs = {
                "stage": "keypoints",
                "category": category,
                "preset": preset.keypoint_preset,
                "overrides": preset.keypoint_overrides,
            }
            kp_dir = out / "keypoints" / category
            keypoint_records[category] = run_stage(
                f"keypoints/{category}",
                kp_dir,
                kp_inputs,
                lambda c=category, d=kp_dir: fns.keypoints(c, preset, d / "run", progress),
                _exists("run_dir"),
            )
            stages.append(keypoint_records[category])
        for policy in policies:
            if policy in YAW_FRAME_POLICIES and task not in HEADING_TASKS:
                _log(f"[benchmark] policy/{task}/{policy}: skipped (a {category} has no heading to turn by)")
                continue
            kp = keypoint_records.get(category) if policy in KEYPOINT_POLICIES else None
            pol_inputs = {
                "stage": "policy",
                "task": task,
                "policy": policy,
                "preset": preset.policy_preset,
                "overrides": preset.policy_overrides,
                "seed": preset.seed,
                "demos": demos["fingerprint"],
                "keypoints": kp["fingerprint"] if kp else None,
            }
            pol_dir = out / "policies" / task / policy
            keypoints = {category: kp["outputs"]["run_dir"]} if kp else None
            trained = run_stage(
                f"policy/{task}/{policy}",
                pol_dir,
                pol_inputs,
                lambda t=task, p=policy, d=pol_dir, k=keypoints, ds=demos["outputs"]["path"]: fns.policy(
                    t, p, preset, ds, k, d / "run", progress
                ),
                _exists("run_dir"),
            )
            stages.append(trained)
            cells = [("seen", preset.demo_split, preset.demo_object_ids)]
            cells.append(("unseen", "test", preset.unseen_ids))
            for label, split, ids in cells:
                for setting in preset.settings:
                    ev_inputs = {
                        "stage": "eval",
                        "policy": trained["fingerprint"],
                        "split": split,
                        "object_ids": list(ids),
                        "setting": setting,
                        "episodes_per_object": preset.episodes_per_object,
                        "seed": preset.eval_seed,
                        "max_steps": preset.eval_max_steps,
                        "num_inference_steps": preset.num_inference_steps,
                        "videos": preset.videos,
                    }
                    ev_dir = out / "eval" / task / policy / f"{label}_{setting}"
                    ev = run_stage(
                        f"eval/{task}/{policy}/{label}_{setting}",
                        ev_dir,
                        ev_inputs,
                        lambda s=split, st=setting, i=ids, d=ev_dir, r=trained["outputs"]["run_dir"]: (
                            _eval_cell(fns, r, s, st, i, preset, d, progress)
                        ),
                        _exists("summary"),
                    )
                    stages.append(ev)
                    summary = json.loads(Path(ev["outputs"]["summary"]).read_text())
                    results.append(
                        {
                            "task": task,
                            "policy": policy,
                            "split": label,
                            "setting": setting,
                            "success_rate": summary["success_rate"],
                            "ci95": summary["ci95"],
                            "episodes": summary["episodes"],
                            "successes": summary["successes"],
                            "by_object": summary.get("by_object", {}),
                            "failures": summary.get("failures", {}),
                        }
                    )
    return {
        "preset": asdict(preset),
        "tasks": list(tasks),
        "policies": list(policies),
        "results": results,
        "stages": [
            {k: s.get(k) for k in ("name", "fingerprint", "reused", "resumed", "seconds", "outputs")}
            for s in stages
        ],
        "seconds": round(time.perf_counter() - t0, 1),
    }


def _eval_cell(fns, run_dir, split, setting, ids, preset, directory: Path, progress) -> dict[str, Any]:
    summary = fns.evaluate(run_dir, split, setting, ids, preset, directory / "results.jsonl", progress)
    path = directory / "summary.json"
    path.write_text(json.dumps(summary, indent=1, default=str))
    return {"summary": str(path), "results": str(directory / "results.jsonl")}
