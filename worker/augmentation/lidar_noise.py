"""The range noise and dropout the object points get, measured once per stretch of frames.

:func:`renderer.lidar_noise.measure_lidar_noise` measures a sensor's range noise and
dropout on the real points in a shell around an object (``NOISE_SHELL_M`` deep). What it
measures is the sensor on the surfaces near the object: it changes as the object comes
nearer or moves, not from one frame to the next. So the plan measures it at *key frames*
only (:func:`noise_key_frames`): the first frame of the range, then the first frame where
some object's bounding-sphere centre has moved more than ``REMEASURE_M`` (half the shell)
in the lidar's base frame since the last key frame, i.e. once half of the shell's points
have changed at most. Every frame uses the estimate of its key frame
(:func:`noise_key_spheres`, :func:`measure_key_noise`); the noise's draw stays per frame
(its seed is the frame). A pool's parent plans without measuring them and measures them
while its children start on the first frames (their camera images come before their
clouds): a frame reads its key's estimate from the plan, from the file the parent shared
(:func:`key_noise`), or measures it itself; the estimate depends on the key frame alone,
so each frame gets the same wherever it is measured.

Measured on 16 full-density frames with the object in every frame
(``scripts/bench_augment.py``): the estimate took 150 ms a frame, a tenth of a frame's
worker time; at a key frame every 5 m of relative motion it is a few per sequence.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from geometry.transforms import invert_T, transform_points
from renderer.lidar_cast import LidarNoise
from renderer.lidar_noise import NOISE_SHELL_M, measure_lidar_noise
from renderer.mesh import ObjectMesh
from worker.osdar.errors import atomic_write_bytes
from worker.osdar.pcd import read_pcd
from worker.osdar.sequence import uri_to_path

if TYPE_CHECKING:  # plan.py imports this module
    from worker.augmentation.plan import Plan, PlannedObject

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: A new key frame once some object moved this far in the base frame (half the shell).
REMEASURE_M = 0.5 * NOISE_SHELL_M
#: Margin added to an object's bounding sphere (the ray cast's and the shell's inner edge).
LIDAR_SPHERE_MARGIN_M = 0.05


def bounding_sphere(mesh: ObjectMesh, T_base_obj: F64) -> tuple[F64, float]:
    """The mesh's bounding sphere in the base frame: centre (3,), radius (m)."""
    b = mesh.bounds
    centre = transform_points(T_base_obj, (0.5 * (b[0] + b[1]))[None])[0]
    return centre, 0.5 * float(np.linalg.norm(b[1] - b[0])) + LIDAR_SPHERE_MARGIN_M


def object_spheres(
    objects: Sequence[PlannedObject], T_world_base: F64, stream: str, frame: int
) -> list[tuple[F64, float]]:
    """Per object its bounding sphere (centre (3,), radius) in the base frame of ``frame``
    at ``stream``'s timestamp; T_world_base : (4, 4) the vehicle pose then."""
    T_base_world = invert_T(T_world_base)
    return [
        bounding_sphere(o.mesh(stream, frame, full=True), T_base_world @ o.pose(stream, frame))
        for o in objects
    ]


def lidar_noise_near(
    fields: Mapping[str, NDArray],
    origins: Mapping[int, F64] | F64,
    spheres: list[tuple[F64, float]],
) -> dict[int, LidarNoise]:
    """The real cloud's range noise and dropout per sensor_index around the objects.

    spheres : per object its bounding sphere (centre (3,), radius) in the base frame;
    :func:`renderer.lidar_noise.measure_lidar_noise` measures each one's shell, and
    with several objects a sensor gets the median of its finite estimates (points
    summed, rings the most found).
    """
    per = [measure_lidar_noise(fields, origins, c, r) for c, r in spheres]
    out: dict[int, LidarNoise] = {}
    for s in sorted({k for est in per for k in est}):
        got = [est[s] for est in per if s in est]
        sig = [g.range_sigma_m for g in got if np.isfinite(g.range_sigma_m)]
        out[s] = LidarNoise(
            float(np.median(sig)) if sig else float("nan"),
            float(np.median([g.dropout for g in got])),
            sum(g.points for g in got),
            max(g.rings for g in got),
        )
    return out


def noise_key_frames(
    centres: Mapping[int, F64], remeasure_m: float = REMEASURE_M
) -> dict[int, int]:
    """frame -> its key frame (module docstring), over the frames of ``centres`` in order.

    centres : frame -> (k, 3) the k objects' sphere centres in that frame's base frame.
    """
    keys: dict[int, int] = {}
    key, ref = None, None
    for f in sorted(centres):
        c = np.asarray(centres[f], dtype=np.float64)
        if ref is None or float(np.max(np.linalg.norm(c - ref, axis=1))) > remeasure_m:
            key, ref = f, c
        keys[f] = int(key)  # type: ignore[arg-type]
    return keys


def noise_key_spheres(
    uris: Mapping[int, Mapping[str, str]],
    stream: str,
    frames: Sequence[int],
    objects: Sequence[PlannedObject],
    T_world_base: Mapping[int, F64],
) -> tuple[dict[int, int], dict[int, F64]]:
    """(frame -> key frame, key frame -> (k, 4) the k objects' bounding spheres: centre
    (3,) and radius, base frame) for the frames with a cloud of ``stream``;
    T_world_base : frame -> (4, 4) the pose at the lidar timestamp."""
    spheres = {
        f: object_spheres(objects, T_world_base[f], stream, f)
        for f in frames
        if stream in uris.get(f, {})
    }
    keys = noise_key_frames({f: np.stack([c for c, _ in s]) for f, s in spheres.items()})
    at_keys = {}
    for k in sorted(set(keys.values())):
        at_keys[k] = np.array([[*c, r] for c, r in spheres[k]], np.float64)
    return keys, at_keys


def measure_key_noise(
    seq_folder: str | Path, uri: str, origins: Mapping[int, F64] | F64, spheres: F64
) -> dict[int, LidarNoise]:
    """{sensor_index: LidarNoise} of the cloud at ``uri`` around ``spheres`` (k, 4) (centre,
    radius; base frame): :func:`lidar_noise_near`."""
    cloud = read_pcd(uri_to_path(Path(seq_folder), uri))
    return lidar_noise_near(cloud.fields, origins, [(sp[:3], float(sp[3])) for sp in spheres])


def _noise_file(plan: Plan, key: int) -> Path | None:
    return Path(plan.lidar_noise_dir) / f"key_{key}.json" if plan.lidar_noise_dir else None


def key_noise(plan: Plan, key: int) -> dict[int, LidarNoise] | None:
    """The lidar noise of key frame ``key``: the plan's, else (a plan made with
    ``measure_noise=False``) the estimate another process shared in
    ``plan.lidar_noise_dir``, else measured here (and shared there). The estimate is a
    function of the key frame's cloud and spheres alone: whichever process measures it,
    every frame gets the same. None: the plan has no noise for that key."""
    got = plan.lidar_noise.get(key)
    if got is not None:
        return got
    spheres = plan.lidar_noise_spheres.get(key)
    if spheres is None or plan.lidar_stream is None or plan.lidar_origins is None:
        return None
    path = _noise_file(plan, key)
    if path is not None and path.is_file():
        got = {int(s): LidarNoise(**v) for s, v in json.loads(path.read_text()).items()}
    else:
        got = measure_key_noise(
            plan.seq_folder, plan.uris[key][plan.lidar_stream], plan.lidar_origins, spheres
        )
        if path is not None:
            text = json.dumps({str(s): dataclasses.asdict(v) for s, v in got.items()})
            atomic_write_bytes(path, text.encode())
    plan.lidar_noise[key] = got
    return got


def measure_pending_noise(plan: Plan) -> int:
    """Measure (and share) every key frame's noise the plan does not hold yet; returns how
    many were measured or read."""
    pending = [k for k in sorted(plan.lidar_noise_spheres) if k not in plan.lidar_noise]
    for k in pending:
        key_noise(plan, k)
    return len(pending)
