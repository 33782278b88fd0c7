"""Procedural railway scenes: presets, determinism, ground-truth elements."""

from __future__ import annotations

import numpy as np
import pytest

from worker.synth.scene_builders import BALLAST_CRIB, SLEEPER_TOP
from worker.synth.scene_mesh import MATERIAL_ID
from worker.synth.scenes import SCENE_NAMES, build_scene


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_presets_build(name: str) -> None:
    sc = build_scene(name, 11, 120.0)
    assert sc.ego is sc.tracks[0] and sc.ego.track_id == 0
    assert len(sc.mesh.faces) < 1_500_000
    assert sc.mesh.faces.max() < len(sc.mesh.vertices)
    assert np.all(np.isfinite(sc.mesh.vertices))
    assert sc.drive_range[1] - sc.drive_range[0] == pytest.approx(120.0)
    assert sc.drive_range[1] < sc.ego.length
    assert sc.speed_mps == 0.0 if name == "stationary" else sc.speed_mps > 0.0
    assert len(sc.landmarks) >= 2 and len(sc.poles) >= 2
    assert len({lm.id for lm in sc.landmarks}) == len(sc.landmarks)
    for m in ("rail", "sleeper", "ballast", "ground"):
        assert np.any(sc.mesh.material == MATERIAL_ID[m])
    if name in ("station", "klein_flottbek", "stationary"):
        assert sc.platforms and np.any(sc.mesh.material == MATERIAL_ID["platform_edge"])


def test_deterministic_from_seed() -> None:
    a = build_scene("switch", 5, 100.0)
    b = build_scene("switch", 5, 100.0)
    c = build_scene("switch", 6, 100.0)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    np.testing.assert_array_equal(a.mesh.material, b.mesh.material)
    assert [lm.xyz.tolist() for lm in a.landmarks] == [lm.xyz.tolist() for lm in b.landmarks]
    assert a.mesh.vertices.shape != c.mesh.vertices.shape or not np.array_equal(
        a.mesh.vertices, c.mesh.vertices
    )


def test_origin_offset_shifts_everything() -> None:
    off = np.array([5.6e5, 5.93e6, 40.0])
    a = build_scene("tight_curve", 3, 100.0, heading=0.3)
    b = build_scene("tight_curve", 3, 100.0, heading=0.3, origin_offset=off)
    np.testing.assert_allclose(b.mesh.vertices - off, a.mesh.vertices, atol=1e-6)
    np.testing.assert_allclose(b.ego.point(50.0) - off, a.ego.point(50.0), atol=1e-8)
    np.testing.assert_allclose(b.landmarks[0].xyz - off, a.landmarks[0].xyz, atol=1e-6)
    np.testing.assert_allclose(b.origin_offset, off)


def test_track_bed_heights() -> None:
    sc = build_scene("straight_sparse", 1, 100.0)
    # rail heads ~0.2 m above the ballast between the sleepers, sleepers just above it
    assert 0.15 <= -BALLAST_CRIB <= 0.22
    assert BALLAST_CRIB < SLEEPER_TOP < -0.17
    faces = sc.mesh.faces[sc.mesh.material == MATERIAL_ID["rail"]]
    z_top = sc.mesh.vertices[np.unique(faces), 2].max()
    assert z_top == pytest.approx(sc.ego.point(0.0)[0, 2], abs=1e-6)
    for pole in sc.poles:
        assert 6.0 < pole.height < 9.0
