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


# ----------------------------------------------------------------- variety and proportions
def test_person_proportions_match_anthropometry() -> None:
    """Standing adults against body-segment proportions (Drillis & Contini 1966; Winter,
    Biomechanics and Motor Control of Human Movement): eye height 0.936 H, crotch
    (inseam) height 0.45-0.48 H, the face's most forward point (nose) about 0.90 H."""
    for seed in range(5):
        p = build_obstacle("person", seed=seed)
        H = p.meta["stature_m"]
        v = p.vertices
        assert abs(p.size[2] / H - 1.0) < 0.01  # the mesh is as tall as its stature
        assert abs(p.meta["eye_height_m"] / H - 0.936) < 0.01
        crotch = v[(np.abs(v[:, 1]) < 0.01) & (v[:, 2] > 0.2 * H) & (v[:, 2] < 0.6 * H), 2].min()
        assert 0.43 <= crotch / H <= 0.49, crotch / H
        head = v[v[:, 2] > 0.88 * H]
        assert 0.87 <= head[np.argmax(head[:, 0]), 2] / H <= 0.95


@pytest.mark.parametrize(
    ("name", "withers_per_length", "belly_per_withers"),
    [
        # Holstein-type cattle: withers 1.3-1.5 m, nose to tail root 2.2-2.6 m, belly
        # 0.6-0.7 m above the ground (a deep barrel)
        ("cow", (0.50, 0.66), (0.40, 0.52)),
        # riding horses, 15-17 hands: withers 1.5-1.7 m, nose to buttock 2.3-2.6 m, belly
        # 0.85-1.0 m (long legs)
        ("horse", (0.58, 0.75), (0.52, 0.65)),
        # Asian elephant: shoulder 2.5-3.0 m, trunk to tail 3.6-4.4 m standing, belly
        # 0.9-1.3 m
        ("elephant", (0.55, 0.80), (0.30, 0.50)),
    ],
)
def test_animal_proportions(name: str, withers_per_length: tuple, belly_per_withers: tuple) -> None:
    for seed in range(3):
        m = build_obstacle(name, seed=seed)
        v = m.vertices
        L = m.size[0]
        top = m.meta.get("withers_m", m.size[2])
        mid = v[(np.abs(v[:, 0]) < 0.08 * L) & (np.abs(v[:, 1]) < 0.05)]  # under the barrel
        belly = mid[:, 2].min()
        assert withers_per_length[0] <= top / L <= withers_per_length[1], (seed, top / L)
        assert belly_per_withers[0] <= belly / top <= belly_per_withers[1], (seed, belly / top)


@pytest.mark.parametrize("pose", obs.PERSON_POSES)
def test_person_poses(pose: str) -> None:
    p = build_obstacle("person", seed=7, pose=pose)
    standing = build_obstacle("person", seed=7)
    assert p.meta["pose"] == pose and p.meta["seed"] == 7
    assert p.meta["stature_m"] == standing.meta["stature_m"]  # the same person
    np.testing.assert_allclose(p.colors.mean(0), standing.colors.mean(0), atol=0.05)
    tm = trimesh.Trimesh(p.vertices, p.faces, process=False)
    assert tm.is_watertight and tm.body_count == 1 and tm.volume > 0
    H = p.meta["stature_m"]
    h, ext = p.size[2] / H, p.size / H
    if pose in ("standing", "walking"):
        assert h > 0.97
    elif pose == "crouching":
        assert 0.45 < h < 0.75  # head about 0.6 H in a deep squat
    elif pose == "sitting":
        assert 0.45 < h < 0.65 and ext[0] > 0.45  # legs out in front
    else:  # lying across the object's y axis, head at +y
        assert h < 0.3 and ext[1] > 0.95 and p.meta["eye_height_m"] < 0.3 * H
        assert p.vertices[np.argmax(p.vertices[:, 1]), 2] > 0.05  # the head, not a foot
    with pytest.raises(ValueError, match="pose"):
        build_obstacle("cow", pose="sitting")


def test_variety_from_the_seed_and_textures() -> None:
    persons = [build_obstacle("person", seed=s) for s in range(6)]
    statures = {round(p.meta["stature_m"], 3) for p in persons}
    assert len(statures) == 6 and max(statures) - min(statures) > 0.1
    looks = {tuple(np.round(p.colors.mean(0), 2)) for p in persons}  # skin and clothes
    assert len(looks) == 6
    cows = [build_obstacle("cow", seed=s) for s in range(4)]
    assert len({c.meta["variant"] for c in cows}) >= 2 or len(
        {tuple(np.round(c.colors.mean(0), 2)) for c in cows}) == 4  # fmt: skip
    for name in NAMES:  # per-pixel detail: triplanar procedural textures by region
        m = build_obstacle(name, seed=0)
        mats, fm = m.surface
        used = {mats[i].name for i in np.unique(fm)}
        assert any(n.endswith("-detail") for n in used), (name, used)
        assert all(mats[i].triplanar_m for i in np.unique(fm) if mats[i].textured)
