import numpy as np
import pytest
import trimesh

from keygen.errors import AssetError
from keygen.objects.meshing import (
    capsule_chain,
    disc_part,
    distance_to_solid,
    revolve_profile,
    ring_wall_parts,
    sweep_tube,
    union,
)


def test_revolve_profile_is_watertight_with_the_right_volume():
    r, h = 0.05, 0.1
    cyl = revolve_profile(np.array([[0, 0], [r, 0], [r, h], [0, h]]), sections=128)
    assert cyl.is_watertight and cyl.is_volume
    assert cyl.volume == pytest.approx(np.pi * r**2 * h, rel=2e-3)
    with pytest.raises(AssetError):
        revolve_profile(np.array([[0, 0], [1, 1]]))


def test_sweep_tube_is_a_closed_volume():
    a = np.linspace(-np.pi / 2, np.pi / 2, 24)
    path = np.stack([0.03 * np.cos(a), np.zeros_like(a), 0.03 * np.sin(a)], axis=1)
    tube = sweep_tube(path, 0.005, 0.004)
    assert tube.is_watertight and tube.is_volume
    length = np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))
    assert tube.volume == pytest.approx(np.pi * 0.005 * 0.004 * length, rel=0.05)


def test_union_of_overlapping_solids_is_watertight():
    a = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    b = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([0.05, 0, 0])
    u = union([a, b])
    assert u.is_watertight
    assert u.volume == pytest.approx(0.15 * 0.1 * 0.1, rel=1e-6)


def test_ring_wall_covers_the_wall_without_gaps():
    parts = ring_wall_parts(np.array([0.0, 0.05]), np.array([0.04, 0.04]), np.array([0.045, 0.045]), 12)
    assert len(parts) == 12
    meshes = [p.to_trimesh() for p in parts]
    assert all(m.is_convex for m in meshes)
    # every point of the true wall lies inside some wedge
    rng = np.random.default_rng(0)
    ang, rad, z = (
        rng.uniform(0, 2 * np.pi, 500),
        rng.uniform(0.0401, 0.0449, 500),
        rng.uniform(0.001, 0.049, 500),
    )
    pts = np.stack([rad * np.cos(ang), rad * np.sin(ang), z], axis=1)
    inside = np.any([m.contains(pts) for m in meshes], axis=0)
    assert inside.all()


def test_disc_and_capsules_and_distance():
    disc = disc_part(0.05, 0.0, 0.01).to_trimesh()
    assert disc.is_convex and disc.volume >= np.pi * 0.05**2 * 0.01
    chain = capsule_chain(np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0]]), 0.01)
    assert len(chain) == 2
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    d = distance_to_solid(box, np.array([[0, 0, 0], [0.1, 0, 0]]))
    assert d[0] == 0 and d[1] == pytest.approx(0.05, abs=1e-6)
