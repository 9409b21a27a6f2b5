"""Perception: multi-view RGB-D plus masks -> fused, cropped, down-sampled point clouds."""

from keygen.perception.fusion import (
    FusionConfig,
    fuse_views,
    make_clouds,
    make_object_cloud,
    make_scene_cloud,
)
from keygen.perception.segmenters import Segmenter, SimulatorSegmenter

__all__ = [
    "FusionConfig",
    "Segmenter",
    "SimulatorSegmenter",
    "fuse_views",
    "make_clouds",
    "make_object_cloud",
    "make_scene_cloud",
]
