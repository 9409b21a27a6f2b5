"""Policy configs: the registry, validation, and the task -> keypointed objects constant."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from keygen.errors import InvalidParameterError, KeyGenError
from keygen.policies import (
    POLICY_NAMES,
    TASK_KEYPOINT_OBJECTS,
    PolicyConfig,
    keypoint_categories,
    make_policy_config,
)
from keygen.policies.training import PRESETS, TrainConfig


def test_registry_covers_every_policy_and_round_trips_through_dicts() -> None:
    for name in POLICY_NAMES:
        cfg = make_policy_config(name)
        assert cfg.name == name
        assert PolicyConfig.from_dict(cfg.to_dict()) == cfg
    assert (
        make_policy_config("keygen").use_keypoints and make_policy_config("keygen").cloud_source == "object"
    )
    assert not make_policy_config("keygen_no_kp").use_keypoints
    assert make_policy_config("keygen_scene").cloud_source == "scene"
    dp3 = make_policy_config("dp3")
    assert (dp3.backbone, dp3.encoder, dp3.cloud_source, dp3.use_keypoints) == ("unet", "dp3", "scene", False)
    yaw = make_policy_config("keygen_yaw")
    assert (yaw.yaw_frame, yaw.yaw_origin, yaw.use_keypoints) == (True, "grasp", True)
    assert make_policy_config("keygen_yaw", yaw_origin="centroid").yaw_origin == "centroid"


def test_torch_free_copies_of_the_policy_names_match_the_registry() -> None:
    # The CLI and the benchmark pipeline keep plain copies so that importing them needs no torch.
    from keygen.cli.train import POLICIES
    from keygen.evaluation.pipeline import HEADING_TASKS as PIPELINE_HEADING_TASKS
    from keygen.evaluation.pipeline import KEYPOINT_POLICIES, YAW_FRAME_POLICIES
    from keygen.policies.config import HEADING_TASKS

    assert POLICIES == POLICY_NAMES
    assert set(KEYPOINT_POLICIES) == {n for n in POLICY_NAMES if make_policy_config(n).use_keypoints}
    assert set(YAW_FRAME_POLICIES) == {n for n in POLICY_NAMES if make_policy_config(n).yaw_frame}
    assert PIPELINE_HEADING_TASKS == HEADING_TASKS


@pytest.mark.parametrize(
    "changes",
    [
        {"horizon": 0},
        {"execute_steps": 17},
        {"width": 130},
        {"scheduler": "euler"},
        {"cloud_source": "rgb"},
        {"inference_steps": 200},
        {"ema_decay": 1.0},
        {"cloud_frames": 3},
    ],
)
def test_bad_policy_configs_are_refused(changes: dict) -> None:
    with pytest.raises(InvalidParameterError):
        make_policy_config("keygen", **changes)


def test_unknown_names_and_fields_are_refused() -> None:
    with pytest.raises(KeyGenError, match="unknown policy"):
        make_policy_config("act")
    with pytest.raises(InvalidParameterError, match="unknown policy config fields"):
        PolicyConfig.from_dict({"name": "keygen", "depthh": 3})
    with pytest.raises(InvalidParameterError, match="divisible"):
        make_policy_config("dp3", horizon=10)


def test_keypoint_objects_match_the_tasks() -> None:
    """The constant names exactly the category objects of each task, with their mask labels."""
    from keygen.sim.env import TASKS, cached_instance, task_class
    from keygen.sim.randomization import Randomization

    assert set(TASK_KEYPOINT_OBJECTS) == set(TASKS)
    for name in TASKS:
        cls = task_class(name)
        task = cls(
            cached_instance(cls.category, "train", 0, 0), "easy", np.random.default_rng(0), Randomization()
        )
        task.populate(mujoco.MjSpec())
        found = tuple((o.asset.category, o.label) for o in task.objects if o.asset is not None)
        assert found == TASK_KEYPOINT_OBJECTS[name], name
        assert keypoint_categories(name) == (cls.category,)
    with pytest.raises(InvalidParameterError, match="task must be one of"):
        keypoint_categories("juggle")


def test_train_config_presets_and_validation(tmp_path) -> None:
    cfg = TrainConfig.from_preset(
        "quick", policy="dp3", dataset=tmp_path / "d.zarr", out=tmp_path / "r", steps=None
    )
    assert cfg.steps == PRESETS["quick"]["steps"] and cfg.preset == "quick"
    assert TrainConfig.from_preset("default", policy="dp3", dataset="d", out="o", steps=7).steps == 7
    for bad in ({"steps": 0}, {"policy": "act"}, {"val_fraction": 1.0}, {"policy_overrides": {"width": 3}}):
        with pytest.raises(InvalidParameterError):
            TrainConfig.from_preset("quick", **({"policy": "dp3", "dataset": "d", "out": "o"} | bad))
    with pytest.raises(InvalidParameterError, match="preset"):
        TrainConfig.from_preset("huge", policy="dp3", dataset="d", out="o")
