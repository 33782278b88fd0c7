"""The three-cornered hat (hat.py) where the sources have biases shared by all pairs
(known answers)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from worker.preparation.localization.hat import hat_variances, relative_difference
from worker.preparation.localization.ins_wander import robust_rms

MDEG = np.pi / 180.0 / 1000.0


def _rel(roll: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(m, 3, 3) relative rotations with the given roll and pitch (rad)."""
    return Rotation.from_euler("xyz", np.c_[roll, pitch, np.zeros(len(roll))]).as_matrix()


def _sources(
    rng: np.random.Generator, m: int, spec: dict[str, tuple[float, float]]
) -> dict[str, np.ndarray]:
    """Per source (bias, white sigma) in mdeg of its roll and pitch over the pairs, about a
    common true motion."""
    truth = rng.normal(0.0, 50.0, (m, 2))
    out = {}
    for name, (bias, sigma) in spec.items():
        e = bias + rng.normal(0.0, sigma, (m, 2))
        out[name] = _rel(*((truth + e) * MDEG).T)
    return out


def test_two_sources_biased_alike_do_not_make_the_third_look_bad() -> None:
    """A good INS (white 4 mdeg, no bias), an odometry drifting by +11 mdeg over the lag and
    ground pairs off by +4 mdeg (the klein_flottbek bogie cell's figures). The formula
    read the product of the INS's two mean disagreements (11 x 4 mdeg^2) as its own; now
    its shared part is at most the smaller disagreement, the ground's 4 mdeg (what it
    would be were the ground unbiased): the INS at most sqrt(4^2 + 4^2) = 5.7 mdeg plus
    sampling noise, where the bare formula gives 7-8."""
    rng = np.random.default_rng(3)
    rel = _sources(rng, 50, {"ins": (0.0, 4.0), "odometry": (11.0, 12.0), "ground": (4.0, 9.0)})
    v = hat_variances(rel)
    assert v is not None
    ins = np.sqrt(v["ins"]) / MDEG
    assert np.all(ins < 6.5), ins
    # the bare formula on the same pairs (RMS about zero, as before)
    ms = {
        (a, b): robust_rms(relative_difference(rel[a], rel[b])[:, :2]) ** 2
        for a, b in (("ins", "odometry"), ("ins", "ground"), ("odometry", "ground"))
    }
    bare = np.sqrt(0.5 * (ms["ins", "odometry"] + ms["ins", "ground"] - ms["odometry", "ground"]))
    assert np.all(bare / MDEG > ins + 1.0), (bare / MDEG, ins)
    # the drifting odometry is still found: its smaller disagreement (7 mdeg to the
    # ground) on top of its scatter
    odo = np.sqrt(v["odometry"]) / MDEG
    assert np.all(odo > 10.0), odo


def test_the_source_that_stands_out_keeps_its_bias() -> None:
    """An INS whose roll and pitch drift +10 mdeg over the lag against an unbiased odometry
    and ground: the hat still puts the 10 mdeg on the INS, not on the others."""
    rng = np.random.default_rng(4)
    rel = _sources(rng, 50, {"ins": (10.0, 3.0), "odometry": (0.0, 8.0), "ground": (0.0, 6.0)})
    v = hat_variances(rel)
    assert v is not None
    ins = np.sqrt(v["ins"]) / MDEG
    assert np.all(np.abs(ins - np.hypot(10.0, 3.0)) < 2.5), ins
    for other, sigma in (("odometry", 8.0), ("ground", 6.0)):
        got = np.sqrt(v[other]) / MDEG
        assert np.all(got < sigma + 2.5), (other, got)
