"""The walk cycles: what moves, what stays, which foot leads (known from the geometry)."""

from __future__ import annotations

import numpy as np
import pytest

from renderer.assets import build_obstacle
from renderer.assets.walk_cycle import gait_phase_of, gait_pose, quadruped_walk_pose, walk_pose


def _feet(v: np.ndarray, H: float, side: float, fore: bool | None = None) -> float:
    """Mean x of the foot vertices (lowest 6 % of the height) on one side (+1 left)."""
    z = v[:, 2] - v[:, 2].min()
    sel = (z < 0.06 * H) & (np.sign(v[:, 1]) == side)
    if fore is not None:
        mid = 0.5 * (v[z < 0.06 * H, 0].min() + v[z < 0.06 * H, 0].max())
        sel &= (v[:, 0] > mid) == fore
    return float(v[sel, 0].mean())


def test_the_persons_legs_and_arms_swing_and_the_head_stays() -> None:
    rest = build_obstacle("person", seed=2)
    H = float(rest.size[2])
    a, b = walk_pose(rest, np.pi / 2), walk_pose(rest, 3 * np.pi / 2)
    for posed in (a, b):  # the lower foot on the ground, the head where it was
        assert posed.vertices[:, 2].min() == pytest.approx(rest.vertices[:, 2].min(), abs=1e-9)
        head = rest.vertices[:, 2] > 0.9 * H
        assert np.abs(posed.vertices[head, :2] - rest.vertices[head, :2]).max() < 1e-9
    # phase pi/2: the left foot leads, the right trails; half a cycle later the other way
    lead = _feet(a.vertices, H, +1.0) - _feet(a.vertices, H, -1.0)
    assert lead > 0.3 * H * np.sin(np.radians(22.0))
    assert _feet(b.vertices, H, +1.0) - _feet(b.vertices, H, -1.0) < -0.3 * H * np.sin(
        np.radians(22.0)
    )
    assert (a.faces == rest.faces).all() and len(a.vertices) == len(rest.vertices)


@pytest.mark.parametrize("name", ["cow", "horse", "elephant"])
def test_a_quadruped_steps_in_diagonal_pairs_and_its_back_stays(name: str) -> None:
    rest = build_obstacle(name)
    H = float(rest.size[2])
    posed = quadruped_walk_pose(rest, np.pi / 2)
    v, r = posed.vertices, rest.vertices
    back = r[:, 2] > 0.75 * H
    assert np.abs(v[back, :2] - r[back, :2]).max() < 1e-9  # the back does not move
    assert v[:, 2].min() == pytest.approx(r[:, 2].min(), abs=1e-9)
    d = {
        (side, fore): _feet(v, H, side, fore) - _feet(r, H, side, fore)
        for side in (1.0, -1.0)
        for fore in (True, False)
    }
    assert d[(1.0, True)] > 0.03 * H and d[(-1.0, False)] > 0.03 * H  # left fore, right hind
    assert d[(-1.0, True)] < -0.03 * H and d[(1.0, False)] < -0.03 * H


def test_the_cycle_follows_the_class() -> None:
    rock = build_obstacle("rock")
    assert gait_pose(rock, 1.0) is rock
    cow = build_obstacle("cow")
    assert gait_phase_of(cow, 0.6 * float(cow.size[0])) == pytest.approx(2 * np.pi)
    person = build_obstacle("person")
    assert gait_phase_of(person, 0.8 * float(person.size[2])) == pytest.approx(2 * np.pi)
