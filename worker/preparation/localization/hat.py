"""Each source's own error from three independent measures of the same relative motion.

With three measures ``a``, ``b``, ``c`` of one quantity whose errors are independent, the
variances of their pairwise differences are sums of two of the three error variances, so
each one follows without any ground truth (the "three-cornered hat" of clock metrology):
``var_a = (var(a - b) + var(a - c) - var(b - c)) / 2``. Here the quantity is the relative
roll and pitch between two frames, measured by the INS, the lidar odometry and the ground
both frames see (:mod:`~worker.preparation.localization.ground_pairs`).

The formula holds for errors that scatter independently from pair to pair. What all the
pairs share - a source's bias over the lag for the whole sequence (an odometry whose
roll drifts at a steady rate, ground pairs read in a cant transition) - is a single
sample, not a scatter: in the formula it enters as the product of a source's two mean
disagreements, and two other sources biased the same way make it large (a train on
bogies, klein_flottbek, 60 frames: odometry +11 and ground +4 mdeg over 10 frames, a
good INS read as 6.6 mdeg of roll error over the lag where it had none, and the fused
roll followed the ground's bias). So the scatter's hat is taken about the differences'
medians, and each source's shared part separately: its smaller mean disagreement with
the other two where it differs from both the same way (exact when the closer one is
unbiased), none where its mean lies between theirs (it is not the one that stands out).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from worker.preparation.localization.ins_wander import robust_rms

F64 = NDArray[np.float64]

#: Fewest frame pairs for an estimate.
MIN_PAIRS = 5


def relative_difference(R_a: F64, R_b: F64) -> F64:
    """(m, 3) rotation vector of ``R_b^T R_a`` for (m, 3, 3) relative rotations (rad)."""
    return Rotation.from_matrix(np.swapaxes(R_b, 1, 2) @ R_a).as_rotvec()


def hat_variances(rel: dict[str, F64], axes: slice = slice(0, 2)) -> dict[str, F64] | None:
    """Per source, the error variance (rad^2) about each of ``axes`` (default roll, pitch).

    rel : three sources' (m, 3, 3) relative rotations of the same m frame pairs.
    Returns None with fewer than MIN_PAIRS pairs. The scatter's variances are floored at
    0 (sampling noise can make the formula negative for a very good source); each
    source's shared part (module docstring) is added as its square.
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
            m = np.median(d, axis=0)
            v[a, b] = v[b, a] = robust_rms(d - m) ** 2
            mean[a, b], mean[b, a] = m, -m
    out = {}
    for a in names:
        b, c = (x for x in names if x != a)
        scatter = np.maximum(0.5 * (v[a, b] + v[a, c] - v[b, c]), 0.0)
        stands_out = np.sign(mean[a, b]) == np.sign(mean[a, c])
        shared = np.where(stands_out, np.minimum(np.abs(mean[a, b]), np.abs(mean[a, c])), 0.0)
        out[a] = scatter + shared**2
    return out
