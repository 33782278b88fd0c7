"""The process pool of an augmentation: warmed workers (GL context, render setups, ray
caster) and the frames handed out one per task while this process works too.

The pool uses the ``forkserver`` start method: each worker gets its own EGL context,
none is ever inherited through ``fork``.
"""

from __future__ import annotations

import hashlib
import logging
import multiprocessing as mp
import os
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from geometry import camera as cam_mod
from geometry.camera import CameraModel
from osdar_platform.settings import get_settings
from worker.augmentation.frame import ChunkResult, augment_frames, camera_renderer
from worker.augmentation.lidar_noise import measure_pending_noise
from worker.augmentation.plan import Plan
from worker.augmentation.records import dump_chunk, dump_plan, load_chunk, read_plan
from worker.evaluation.object_error import measure_chunk
from worker.orchestration.malloc_tuning import tune_malloc

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: ``progress(done, total)`` in frames.
Progress = Callable[[int, int], None]


# ---------------------------------------------------------------------------- the step
def pool_context() -> Any:
    """``forkserver`` (a clean server imports the heavy modules once; workers fork from it
    without any GL or open3d state), ``spawn`` where forkserver does not exist."""
    try:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(["worker.augmentation.frame"])
        return ctx
    except ValueError:
        return mp.get_context("spawn")


def default_setup_cache() -> Path:
    """Where camera render setups are cached: ``render_setup`` in the workers' cache
    (``Settings.cache_dir``: ``$OSDAR_AR_CACHE_DIR``, default ``<data_dir>/cache``)."""
    return get_settings().cache_dir / "render_setup"


def load_render_setup(cam: CameraModel, cache_dir: str | Path | None) -> None:
    """Fill the renderer's in-process cache of ``cam``'s render setup (the undistorted
    pinhole and its remap, ~2 s to compute at 12 MP) from a disk cache, computing and
    storing it there on a miss. The remap depends only on the intrinsics, so every job
    on the same cameras shares it.

    Uses geometry.camera's private cache (``_SETUP_CACHE``, ``_camera_key``): the
    renderer has no public hook for a precomputed setup.
    """

    margin = 2.0  # CameraModel.render_setup's default margin_px, as ObjectRenderer uses
    key = cam_mod._camera_key(cam, margin)
    if key in cam_mod._SETUP_CACHE or cache_dir is None:
        return

    digest = hashlib.sha256(repr((key[0], key[1], key[4])).encode() + key[2] + key[3])
    path = Path(cache_dir) / f"{digest.hexdigest()[:32]}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                cam_mod._SETUP_CACHE[key] = cam_mod.RenderSetup(
                    K=z["K"], width=int(z["size"][0]), height=int(z["size"][1]),
                    map_x=z["map_x"], map_y=z["map_y"],
                )  # fmt: skip
            return
        except (OSError, ValueError, KeyError) as exc:
            log.warning("render setup cache %s unreadable (%s): recomputing", path, exc)
    setup = cam.render_setup(margin)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, K=setup.K, size=np.array([setup.width, setup.height]),
                     map_x=setup.map_x, map_y=setup.map_y)  # fmt: skip
        os.replace(tmp, path)
    except OSError as exc:
        log.debug("render setup not cached: %s", exc)


def _warm_worker(cameras: list[dict[str, Any]], antialias: str, setup_cache: str | None) -> int:
    """Create the worker's GL context, renderers (render setups) and ray caster ahead."""

    for c in cameras:
        cam = CameraModel.from_json(c)
        load_render_setup(cam, setup_cache)
        camera_renderer(cam, antialias)
    scene = o3d.t.geometry.RaycastingScene()
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    scene.add_triangles(o3d.core.Tensor(tri), o3d.core.Tensor(np.array([[0, 1, 2]], np.uint32)))
    scene.cast_rays(o3d.core.Tensor(np.array([[0.2, 0.2, 1, 0, 0, -1]], np.float32)))
    return os.getpid()


def start_pool(
    workers: int,
    cameras: list[CameraModel] | None = None,
    antialias: str = "auto",
    setup_cache: str | Path | None = None,
) -> Any:
    """A process pool for :func:`augment`, warmed with the cameras (GL context, render
    setups from ``setup_cache``) while the parent plans."""
    pool = ProcessPoolExecutor(
        max_workers=workers, mp_context=pool_context(), initializer=tune_malloc
    )
    cams = [c.to_json() for c in cameras or []]
    cache = None if setup_cache is None else str(setup_cache)
    for _ in range(workers):
        pool.submit(_warm_worker, cams, antialias, cache)
    return pool


_PLAN_CACHE: dict[str, Plan] = {}


def _augment_frames_from_file(
    plan_file: str, frames: list[int], out_root: str, evaluate: bool = False
) -> bytes:
    """In a pool process: the frames of the plan in ``plan_file``; the chunk's records
    come back as a record (:mod:`.records`), the plan goes in as one: nothing a process
    receives is unpickled into code."""
    plan = _PLAN_CACHE.get(plan_file)
    if plan is None:
        _PLAN_CACHE.clear()
        plan = _PLAN_CACHE[plan_file] = read_plan(plan_file)
    return dump_chunk(_augment(plan, frames, out_root, evaluate))


def _augment(plan: Plan, frames: list[int], out_root: str | Path, evaluate: bool) -> ChunkResult:
    """The frames, and with ``evaluate`` their object errors (:func:`.measure_chunk`)."""
    chunk = augment_frames(plan, frames, out_root)
    if evaluate:
        measure_chunk(plan, chunk)
    return chunk


def frame_order(frames: list[int], n_children: int) -> list[int]:
    """The order frames are handed out in (the first 2 n_children go to the children,
    the next to this process): the first frame, whose images the plan decoded in this
    process for the lighting (:func:`.plan.take_decoded`), comes right after the
    children's, so this process composites it without decoding it again."""
    if n_children <= 0 or len(frames) <= 2 * n_children:
        return list(frames)
    k = 2 * n_children
    return [*frames[1 : k + 1], frames[0], *frames[k + 1 :]]


def run_frames(
    plan: Plan, scratch: Path, pool: Any, progress: Progress | None, *, evaluate: bool = False
) -> list[ChunkResult]:
    """All frames of the plan, one per task. With a pool of n - 1 processes, this
    process is the n-th worker: it takes frames itself while the others start up and
    between collecting their results (each child keeps two frames queued). ``evaluate``:
    each frame's object errors are measured where it is augmented."""
    total = len(plan.frames)
    n_children = 0 if pool is None else pool._max_workers
    pending = list(reversed(frame_order(plan.frames, n_children)))
    chunks: list[ChunkResult] = []

    def report() -> None:
        if progress is not None:
            progress(len(chunks), total)

    if pool is None:
        while pending:
            chunks.append(_augment(plan, [pending.pop()], scratch, evaluate))
            report()
        return chunks
    # The plan goes to the workers once, as a file; each task names it.
    plan_file = scratch / ".plan.npz"
    plan_file.write_bytes(dump_plan(plan))
    futures: set[Future] = set()
    noise_done = not plan.lidar_noise_spheres
    while pending or futures:
        while pending and len(futures) < 2 * n_children:
            f = pending.pop()
            futures.add(
                pool.submit(_augment_frames_from_file, str(plan_file), [f], str(scratch), evaluate)
            )
        if not noise_done:
            # the key frames the plan left: measured (and shared) here while the children
            # render their first frames' images, which come before the clouds
            tic = time.perf_counter()
            measure_pending_noise(plan)
            plan.timings["lidar_noise_parent"] = time.perf_counter() - tic
            noise_done = True
        if pending:
            chunks.append(_augment(plan, [pending.pop()], scratch, evaluate))
            report()
            timeout = 0.0
        else:
            timeout = None
        done, futures = wait(futures, timeout=timeout, return_when=FIRST_COMPLETED)
        for fut in done:
            chunks.append(load_chunk(fut.result(), "a pool process's chunk"))
            report()
    return chunks
