"""Running a trained policy in an environment: observation history, action queue, receding horizon.

Timeline with obs history H = 2, horizon T = 16 and execute_steps n = 8::

    env step      t-1   t    t+1  ...  t+7   t+8   t+9 ...
    observations   o    o                     o     o        (the last H are kept)
    query               ^ predicts a_t .. a_{t+15}   ^ predicts a_{t+8} .. a_{t+23}
    executed            a_t  a_{t+1} ... a_{t+7}     a_{t+8} ...

Receding-horizon execution runs the first n of the T predicted actions, then queries again with a
fresh history; ``execute_steps = horizon`` is the whole-trajectory mode (run the full chunk).
After :meth:`PolicyRunner.reset` the history is filled by repeating the first observation, as the
training windows pad an episode's start.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from keygen.data.store import (
    OBJECT_CLOUD_IDS_KEY,
    OBJECT_CLOUD_KEY,
    PROPRIO_KEY,
    SCENE_CLOUD_KEY,
    EpisodeStore,
)
from keygen.errors import InvalidParameterError
from keygen.policies import features
from keygen.policies.checkpoint import KEYPOINTS_DIR, load_policy
from keygen.policies.coherence import COHERENCE_DECAY, check_samples, choose_coherent
from keygen.policies.diffusion import DiffusionPolicy
from keygen.policies.robot_base import base_in_frame
from keygen.policies.size_frame import (
    SizeFrame,
    cached_episode_ends,
    reference_spread,
    rest_axis_references,
    size_mode,
)
from keygen.policies.target_frame import measure_target_frame, target_points
from keygen.policies.target_token import measure_target, target_in_frame
from keygen.policies.yaw_frame import YawFrame, read_origin_keypoint, read_reference

_RAW_KEYS = (PROPRIO_KEY, OBJECT_CLOUD_KEY, OBJECT_CLOUD_IDS_KEY, SCENE_CLOUD_KEY)


class PolicyRunner:
    """A trained policy as a controller: ``act(obs) -> (10,)`` absolute tcp target per env step."""

    def __init__(
        self,
        model: DiffusionPolicy,
        task: str,
        keypoints: features.KeypointSource | None = None,
        execute_steps: int | None = None,
        num_inference_steps: int | None = None,
        seed: int = 0,
        device: str = "cpu",
        size_reference: float | tuple[float, float] | None = None,
        yaw_reference: np.ndarray | None = None,
        yaw_origin_keypoint: int | None = None,
        samples: int = 1,
        coherence_decay: float = COHERENCE_DECAY,
    ):
        self.model = model.eval()
        self.config = model.config
        self.task = task
        self.policy_name = self.config.name
        self.keypoints = keypoints
        if self.config.use_keypoints and keypoints is None:
            raise InvalidParameterError(f"policy {self.policy_name!r} needs a KeypointSource")
        if size_reference is not None and not (
            self.config.use_keypoints and np.all(np.asarray(size_reference, dtype=float) > 0)
        ):
            raise InvalidParameterError(
                f"a size frame needs a keypoint policy and reference spreads > 0; got policy "
                f"{self.policy_name!r} and {size_reference!r}"
            )
        # With a reference (the training data's keypoint spread, or its horizontal and vertical
        # spreads at rest for the per-axis frame), each episode runs in a copy of the scene scaled to
        # the training object's size (keygen.policies.size_frame).
        self.size_reference = size_reference
        self.size_frame: SizeFrame | None = None
        # A policy trained in keypoint yaw frames (keygen.policies.yaw_frame) runs each episode in the
        # frame measured at its first query, with the reference its training wrote.
        # A target yaw frame (keygen.policies.target_frame) is measured on the placement target's
        # points instead and needs no reference.
        keypoint_yaw = self.config.yaw_frame and self.config.yaw_source == "keypoints"
        if keypoint_yaw != (yaw_reference is not None):
            raise InvalidParameterError(
                f"policy {self.policy_name!r} has yaw_frame={self.config.yaw_frame} measured on "
                f"{self.config.yaw_source}: a yaw reference is needed exactly when it was trained in "
                f"keypoint yaw frames"
            )
        if (self.config.yaw_origin == "grasp") != (yaw_origin_keypoint is not None):
            raise InvalidParameterError(
                f"policy {self.policy_name!r} has yaw_origin={self.config.yaw_origin!r}: an origin keypoint "
                f"is needed exactly when its yaw frame is centred on the grasp"
            )
        self.yaw_reference = None if yaw_reference is None else np.asarray(yaw_reference, dtype=np.float64)
        self.yaw_origin_keypoint = yaw_origin_keypoint
        self.yaw_frame: YawFrame | None = None
        # Inputs in metres that the size frame does not scale (it would have to, to stay consistent).
        unscaled = [
            name
            for name, on in (
                ("a target token", self.config.target_token),
                ("a robot-base input", self.config.robot_base),
            )
            if on
        ]
        if unscaled and size_reference is not None:
            raise InvalidParameterError(
                f"policy {self.policy_name!r} has {' and '.join(unscaled)}; the size frame would have to "
                f"scale it too, which is not built: run it without size normalisation"
            )
        # A target-token policy (keygen.policies.target_token) measures the target at its first query.
        self.target: np.ndarray | None = None
        self.num_inference_steps = num_inference_steps or self.config.inference_steps
        self.device = device
        self._execute_steps = self.config.execute_steps
        if execute_steps is not None:
            self.execute_steps = execute_steps
        # Candidates drawn per query; with more than one, the one that agrees best with the previous
        # plan runs (keygen.policies.coherence).
        check_samples(samples)
        if not 0.0 < coherence_decay <= 1.0:
            raise InvalidParameterError(f"coherence_decay must be in (0, 1], got {coherence_decay!r}")
        self.samples = samples
        self.coherence_decay = float(coherence_decay)
        self.last_keypoints: np.ndarray | None = None
        self.last_plan: np.ndarray | None = None  # (T, 10) the latest predicted trajectory
        self._last_normalised_plan: np.ndarray | None = None  # the same in the denoised space
        self._history: deque[dict] = deque(maxlen=self.config.obs_horizon)
        self._queue: deque[np.ndarray] = deque()
        self.reset(seed)

    @property
    def horizon(self) -> int:
        return self.config.horizon

    @property
    def execute_steps(self) -> int:
        return self._execute_steps

    @execute_steps.setter
    def execute_steps(self, n: int) -> None:
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= self.horizon:
            raise InvalidParameterError(f"execute_steps must be an int in [1, {self.horizon}], got {n!r}")
        self._execute_steps = n

    def reset(self, seed: int | None = None) -> None:
        """Clear the observation history and the action queue; reseed the sampling noise if given."""
        self._history.clear()
        self._queue.clear()
        self.last_keypoints = None
        self.last_plan = None
        self._last_normalised_plan = None
        self.size_frame = None
        self.yaw_frame = None
        self.target = None
        if seed is not None or not hasattr(self, "_generator"):
            self._generator = torch.Generator(device=self.device).manual_seed(
                0 if seed is None else int(seed)
            )

    def _frame(self, obs: Mapping[str, np.ndarray]) -> dict:
        # Raw arrays are copied (envs may reuse buffers); features are computed only when a query needs them.
        return {"raw": {k: np.array(obs[k]) for k in _RAW_KEYS if k in obs}, "feats": None}

    def _fill_features(self, frames: list[dict]) -> None:
        # Frames not yet featurised (at most H per query), in one extractor call per object.
        todo = list({id(f): f for f in frames if f["feats"] is None}.values())
        computed = features.steps_features([f["raw"] for f in todo], self.config, self.keypoints)
        for frame, feats in zip(todo, computed, strict=True):
            frame["feats"] = feats

    def predict(self) -> np.ndarray:
        """Sample a trajectory (T, 10) from the current history (filled by :meth:`observe`)."""
        if not self._history:
            raise InvalidParameterError("no observation yet; call act(obs) (or observe(obs)) first")
        frames = list(self._history)
        frames = [frames[0]] * (self.config.obs_horizon - len(frames)) + frames  # pad like training
        self._fill_features(frames)
        feats = [f["feats"] for f in frames]
        model_feats = feats
        # Frames are fixed at the episode's first query (the object at rest): yaw first, as in
        # training, then the size frame measured in it (scaling commutes with the turn).
        k = self.keypoints.num_keypoints if self.keypoints is not None else 0
        if self.config.yaw_frame:
            if self.yaw_frame is None and self.yaw_reference is not None:
                self.yaw_frame = YawFrame.measure(
                    feats[-1]["keypoints"][:k], self.yaw_reference, self.yaw_origin_keypoint
                )
            elif self.yaw_frame is None:
                raw = frames[-1]["raw"]
                self.yaw_frame = measure_target_frame(
                    target_points(raw[OBJECT_CLOUD_KEY], raw[OBJECT_CLOUD_IDS_KEY])
                )
            model_feats = [self.yaw_frame.to_policy(f) for f in model_feats]
        if self.size_reference is not None:
            if self.size_frame is None:
                raw = frames[-1]["raw"]
                label = self.keypoints.objects[0][1]  # the manipulated object (label 1)
                points = features.object_points(raw[OBJECT_CLOUD_KEY], raw[OBJECT_CLOUD_IDS_KEY], label)
                if self.yaw_frame is not None:
                    points = self.yaw_frame.points(points)
                measure = (
                    SizeFrame.measure_axes if isinstance(self.size_reference, tuple) else SizeFrame.measure
                )
                self.size_frame = measure(model_feats[-1]["keypoints"][:k], points, self.size_reference)
                if self.yaw_origin_keypoint is not None:
                    # A grasp-centred policy learnt the handle at its frame's origin: scale about the
                    # grasp, which then stays there, rather than about the keypoint centroid.
                    self.size_frame = self.size_frame.about_xy(np.zeros(2))
            model_feats = [self.size_frame.to_policy(f) for f in model_feats]
        model_inputs = features.stack_history(model_feats, self.config)
        if self.config.target_token:
            if self.target is None:
                self.target = measure_episode_target(frames[-1]["raw"])
            target = self.target if self.yaw_frame is None else target_in_frame(self.target, self.yaw_frame)
            model_inputs["target"] = torch.from_numpy(np.asarray(target, dtype=np.float32))[None]
        if self.config.robot_base:
            assert self.yaw_frame is not None  # the config demands a yaw frame
            model_inputs["base"] = torch.from_numpy(base_in_frame(self.yaw_frame))[None]
        inputs = {k: v.to(self.device) for k, v in model_inputs.items()}
        plans = self.model.predict(
            inputs,
            generator=self._generator,
            num_inference_steps=self.num_inference_steps,
            num_samples=self.samples,
        )
        if self.config.use_keypoints:
            self.last_keypoints = feats[-1]["keypoints"].copy()
        choice = 0
        if self.samples > 1:
            # Compared in the episode's fixed policy frame, before the plan goes back to the world.
            normalised = self.model.normalizer.normalize_action(plans).cpu().numpy()
            choice = choose_coherent(
                normalised, self._last_normalised_plan, self.execute_steps, self.coherence_decay
            )
            self._last_normalised_plan = normalised[choice]
        self.last_plan = plans[choice].cpu().numpy()
        if self.size_frame is not None:
            self.last_plan = self.size_frame.to_world(self.last_plan)
        if self.yaw_frame is not None:
            self.last_plan = self.yaw_frame.to_world(self.last_plan)
        return self.last_plan

    def observe(self, obs: Mapping[str, np.ndarray]) -> None:
        self._history.append(self._frame(obs))

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Record ``obs``; return the next queued action, querying the policy when the queue is empty."""
        self.observe(obs)
        if not self._queue:
            self._queue.extend(self.predict()[: self.execute_steps])
        return self._queue.popleft().astype(np.float32)


def measure_episode_target(raw: Mapping[str, np.ndarray]) -> np.ndarray:
    """The (5,) world target token of an observation (its object cloud and labels)."""
    missing = [k for k in (OBJECT_CLOUD_KEY, OBJECT_CLOUD_IDS_KEY) if k not in raw]
    if missing:
        raise InvalidParameterError(
            f"a target-token policy measures the target on the labelled object cloud; the observation "
            f"lacks {missing}"
        )
    return measure_target(target_points(raw[OBJECT_CLOUD_KEY], raw[OBJECT_CLOUD_IDS_KEY]))


def _dataset_episode_ends(meta: dict) -> np.ndarray:
    """The episode boundaries of the dataset a run was trained on (named in its config.json)."""
    dataset = Path(str(meta.get("train", {}).get("dataset", "")))
    if not dataset.is_dir():
        raise InvalidParameterError(
            f"the per-axis size frame takes the training object at rest from the first step of each "
            f"training episode, and the run's dataset {str(dataset)!r} is not there"
        )
    return EpisodeStore(
        dataset, mode="r", max_episodes=meta.get("train", {}).get("max_episodes")
    ).episode_ends


def load_runner(
    run_dir: str | Path,
    device: str = "cpu",
    num_inference_steps: int | None = None,
    execute_steps: int | None = None,
    seed: int = 0,
    size_normalize: bool | str = False,
    samples: int = 1,
) -> PolicyRunner:
    """A runner for the trained policy in ``run_dir`` (with its copied keypoint extractors).

    ``size_normalize`` (``True`` or ``"uniform"``, or ``"axes"`` for width and height apart) runs each
    episode in the keypoint-measured size frame (:mod:`keygen.policies.size_frame`; keypoint
    policies only). The per-axis frame reads the training episodes' boundaries from the run's keypoint
    cache (from the run's dataset for runs whose cache predates them). ``samples`` > 1 draws that many
    trajectories per query and runs the one that agrees best with the previous plan
    (:mod:`keygen.policies.coherence`)."""
    mode = size_mode(size_normalize)
    run_dir = Path(run_dir)
    model, meta = load_policy(run_dir, device)
    source = None
    if model.config.use_keypoints:
        extractors = {
            c: features.load_extractor(run_dir / KEYPOINTS_DIR / c, device)
            for c in meta["keypoint_categories"]
        }
        source = features.KeypointSource(meta["task"], extractors)
    reference = None
    if mode is not None:
        if source is None:
            raise InvalidParameterError(
                f"size normalisation measures the object by its keypoints; policy "
                f"{model.config.name!r} has none"
            )
        if mode == "uniform":
            reference = reference_spread(run_dir, source.num_keypoints)
        else:
            # Runs trained before the keypoint cache kept the episode boundaries read them from
            # their dataset.
            ends = cached_episode_ends(run_dir)
            if ends is None:
                ends = _dataset_episode_ends(meta)
            reference = rest_axis_references(run_dir, source.num_keypoints, ends)
    keypoint_yaw = model.config.yaw_frame and model.config.yaw_source == "keypoints"
    yaw_reference = read_reference(run_dir) if keypoint_yaw else None
    origin_keypoint = read_origin_keypoint(run_dir) if keypoint_yaw else None
    return PolicyRunner(
        model,
        meta["task"],
        source,
        execute_steps,
        num_inference_steps,
        seed,
        device,
        reference,
        yaw_reference,
        origin_keypoint,
        samples,
    )
