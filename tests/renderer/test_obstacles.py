"""Tests of the obstacle library (renderer/assets/obstacles.py, sdf.py) and LOD (lod.py)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from renderer.assets import obstacles as obs
from renderer.assets.lod import (
    MAX_FACES,
    MIN_FACES,
    choose_detail,
    mask_change,
    rasterize,
    simplify,
)
from renderer.assets.obstacles import OBSTACLES, build_obstacle

NAMES = list(OBSTACLES)


@pytest.mark.parametrize("name", NAMES)
def test_sizes_and_closed_outward_mesh(name: str) -> None:
    for seed in (0, 1, 2):
        m = build_obstacle(name, seed=seed)
        assert m.name == name
        for key, (lo, hi) in OBSTACLES[name].ranges.items():
            assert lo <= m.meta[key] <= hi, (name, seed, key, m.meta[key])
        np.testing.assert_allclose(m.meta["height_m"], m.size[2])
        assert 5_000 <= len(m.faces) <= 30_000
        assert abs(m.vertices[:, 2].min()) < 1e-12
        lo, hi = m.bounds
        np.testing.assert_allclose(0.5 * (lo[:2] + hi[:2]), 0.0, atol=1e-9)
        tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
        assert tm.is_watertight and tm.is_winding_consistent
        assert tm.volume > 0.0  # faces outward
        assert tm.body_count == 1
        assert m.colors.dtype == np.float32 and np.all((m.colors >= 0) & (m.colors <= 1))
        assert np.all((m.reflectivity > 0) & (m.reflectivity <= 1))
        if name != "rock":
            assert len(m.meta["regions"]) >= 3


def test_person_and_animals_look_like_themselves() -> None:
    p = build_obstacle("person", seed=3)
    assert {"skin", "hair", "trousers", "shoes"} <= set(p.meta["regions"])
    head = p.vertices[:, 2] > 0.9 * p.meta["height_m"]
    assert p.size[0] < 0.7 and p.size[1] < 0.8  # upright, slim
    assert len(np.unique(p.colors[head].round(3), axis=0)) > 1  # face and hair differ
    cow, horse, ele = (build_obstacle(n, seed=0) for n in ("cow", "horse", "elephant"))
    assert cow.size[0] > cow.size[2] and ele.size[0] > ele.size[2]
    assert horse.meta["withers_m"] > cow.meta["withers_m"] and "mane" in horse.meta["regions"]
    assert ele.meta["height_m"] > horse.meta["height_m"] and "ear" in ele.meta["regions"]
    assert ele.meta["osdar_class"] == "animal" and p.meta["osdar_class"] == "person"
    tree = build_obstacle("fallen_tree", seed=0)
    assert tree.size[0] > 2.5 * tree.size[2] and "foliage" in tree.meta["regions"]


def test_deterministic_from_seed_and_scaled() -> None:
    a = build_obstacle("cow", seed=7)
    obs._build_cached.cache_clear()
    b = build_obstacle("cow", seed=7)
    c = build_obstacle("cow", seed=8)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.colors, b.colors)
    assert not np.array_equal(a.size, c.size)
    a.vertices[:] = 0.0  # a private copy: the cache is unaffected
    assert np.ptp(build_obstacle("cow", seed=7).vertices) > 0
    s = build_obstacle("cow", seed=7, scale=2.0)
    np.testing.assert_allclose(s.size, 2.0 * b.size)
    assert s.meta["withers_m"] == pytest.approx(2.0 * b.meta["withers_m"])
    assert build_obstacle("tree", seed=1).name == "fallen_tree"
    lo = build_obstacle("person", seed=1, detail=0.5)
    assert len(lo.faces) < 0.4 * len(build_obstacle("person", seed=1).faces)
    with pytest.raises(ValueError, match="unknown obstacle"):
        build_obstacle("giraffe")


def ortho_mask(v: np.ndarray, faces: np.ndarray, axis: int, px: float, lo, shape) -> np.ndarray:
    """Orthographic silhouette along ``axis`` (1 = side view, 0 = front view)."""
    keep = [i for i in range(3) if i != axis]
    uv = v[:, keep] * px
    uv[:, 1] = -uv[:, 1]
    return rasterize(uv, faces, lo, shape)


@pytest.mark.parametrize("name", NAMES)
def test_lod_halves_faces_keeps_silhouette(name: str) -> None:
    m = build_obstacle(name, seed=0, detail=0.8)
    half = simplify(m, len(m.faces) // 2)
    assert len(half.faces) <= 0.55 * len(m.faces)
    assert half.colors.shape == (len(half.vertices), 3) and half.name == name
    # colours carried over: the same palette
    assert np.isin(half.colors.round(4), m.colors.round(4)).all()
    px = 240.0 / float(m.size.max())
    for axis in (0, 1):
        keep = [i for i in range(3) if i != axis]
        uv = m.vertices[:, keep] * px
        lo = np.array([uv[:, 0].min(), -uv[:, 1].max()]) - 4
        shape = (int(np.ptp(uv[:, 1])) + 9, int(np.ptp(uv[:, 0])) + 9)
        a = ortho_mask(m.vertices, m.faces, axis, px, lo, shape)
        b = ortho_mask(half.vertices, half.faces, axis, px, lo, shape)
        assert mask_change(a, b)["iou"] > 0.95


def test_simplify_noop_and_choose_detail() -> None:
    m = build_obstacle("rock", seed=0, detail=0.5)
    same = simplify(m, 10 * len(m.faces))
    assert np.array_equal(same.vertices, m.vertices) and same is not m
    assert choose_detail(0.0) == MIN_FACES and choose_detail(float("nan")) == MIN_FACES
    assert choose_detail(1e6) == MAX_FACES
    h = [1, 10, 100, 164, 500, 2000]
    f = [choose_detail(x) for x in h]
    assert f == sorted(f) and MIN_FACES <= f[3] <= 10_000
