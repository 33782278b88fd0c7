"""Each source's own error from three independent measures of the same relative motion.

With three measures ``a``, ``b``, ``c`` of one quantity whose errors are independent, the
variances of their pairwise differences are sums of two of the three error variances, so
each one follows without any ground truth (the "three-cornered hat" of clock metrology):
``var_a = (var(a - b) + var(a - c) - var(b - c)) / 2``. Here the quantity is the relative
roll and pitch between two frames, measured by the INS, the lidar odometry and the ground
both frames see (:mod:`~worker.preparation.localization.ground_pairs`).

With the differences' means (over the pairs, which share them) the formula splits into
the hat of their scatter about the means and, for source ``a``, the product of its two
mean disagreements ``m_ab m_ac``: exact when the other two are unbiased. Where ``a``
differs from both the same way, two other sources biased alike make that product large
(a train on bogies, klein_flottbek, 60 frames: odometry +11 and ground +4 mdeg of roll
over 10 frames, a good INS read as 6.6 mdeg of roll error over the lag where its error
was its white noise, and the fused roll over 30 frames followed the ground's bias); then
the shared part is taken as the smaller disagreement squared, exact when only the
closer of the other two is unbiased (never more than the product).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from worker.preparation.localization.ins_wander import inliers

F64 = NDArray[np.float64]

#: Fewest frame pairs for an estimate.
MIN_PAIRS = 5


def relative_difference(R_a: F64, R_b: F64) -> F64:
    """(m, 3) rotation vector of ``R_b^T R_a`` for (m, 3, 3) relative rotations (rad)."""
    return Rotation.from_matrix(np.swapaxes(R_b, 1, 2) @ R_a).as_rotvec()


def hat_variances(rel: dict[str, F64], axes: slice = slice(0, 2)) -> dict[str, F64] | None:
    """Per source, the error variance (rad^2) about each of ``axes`` (default roll, pitch).

    rel : three sources' (m, 3, 3) relative rotations of the same m frame pairs.
    Returns None with fewer than MIN_PAIRS pairs. Variances are floored at 0 (sampling
    noise can make the formula negative for a very good source); a source's part shared
    by all pairs is counted as the module docstring says.
    """
    names = list(rel)
    if len(names) != 3:
        raise ValueError(f"the three-cornered hat needs 3 sources, got {names}")
    if len(rel[names[0]]) < MIN_PAIRS:
        return None
    v, mean = {}, {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            d = relative_difference(rel[a], rel[b])[:, axes]
            keep = inliers(d)  # as robust_rms: a few jumps do not count
            n = np.maximum(keep.sum(axis=0), 1)
            m = np.sum(np.where(keep, d, 0.0), axis=0) / n
            v[a, b] = v[b, a] = np.sum(np.where(keep, d * d, 0.0), axis=0) / n - m * m
            mean[a, b], mean[b, a] = m, -m
    out = {}
    for a in names:
        b, c = (x for x in names if x != a)
        scatter = 0.5 * (v[a, b] + v[a, c] - v[b, c])
        product = mean[a, b] * mean[a, c]
        smaller = np.minimum(np.abs(mean[a, b]), np.abs(mean[a, c]))
        shared = np.where(product > 0.0, smaller**2, product)
        out[a] = np.maximum(scatter + shared, 0.0)
    return out
