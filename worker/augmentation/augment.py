"""Pipeline steps 3-7: a virtual object in every frame of a sequence, cameras and lidar.

The recipe, per frame (:func:`augment_frame`)::

    for each camera: pose at its timestamp -> render -> (not visible: link the file)
                     -> decode -> composite (ROI only) -> encode -> write
    lidar:           pose at the lidar timestamp -> read -> cast rays near the object
                     -> (no hit: link the file) -> write (the input's DATA type)
    annotation:      cuboid in the lidar frame, bbox + poly2d per camera, lidar indices

Everything frame-independent is done once by :func:`plan_augmentation` (object mesh and
its level of detail, placement, proxies, lighting per camera, poses at every sensor
timestamp) into a picklable :class:`Plan`. The chunk API is what a Celery chord uses:
``plan_augmentation`` once, :func:`augment_frames` per chunk of frames (any process or
machine that sees the sequence and a scratch folder), :func:`finish_augmentation` once
(moves the chunks' files into the output, copies every other input file byte-identically,
adds the annotations to the labels, writes ``metrics.json``, renames into place).
:func:`augment` runs all three here, the frames in a process pool (``workers``).

Files not touched are hard links (or byte copies) of the input: frames where the object
is not visible in a camera cost no PNG decode or encode, which is what keeps a job close
to its I/O floor (BENCHMARK.md). The process pool uses the ``forkserver`` start method:
each worker gets its own EGL context, none is ever inherited through ``fork``."""

from __future__ import annotations

import json
import logging
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from geometry.camera import CameraModel, load_cameras
from worker.augmentation.finish import METRICS_FILE, finish_augmentation
from worker.augmentation.placement import (
    PlacementError,
)
from worker.augmentation.plan import AugmentError, plan_augmentation, sequence
from worker.augmentation.pool import (
    Progress,
    default_setup_cache,
    load_render_setup,
    run_frames,
    start_pool,
)
from worker.augmentation.spec import AugmentSpec
from worker.json_values import jsonable
from worker.preparation.calibration_point import Clicks
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import prepare

log = logging.getLogger(__name__)


def _spec_cameras(seq_folder: str | Path, spec: AugmentSpec) -> list[CameraModel]:
    """The spec's cameras of a sequence ([] when the spec cannot be honoured: the plan
    reports that)."""
    try:
        seq = sequence(seq_folder)
        names = spec.camera_names(seq.cameras)
        return list(load_cameras(seq.labels.raw, names).values())
    except (ValueError, OSError):
        return []


def augment(
    seq_folder: str | Path,
    spec: AugmentSpec,
    out_folder: str | Path,
    *,
    prepared: Any = None,
    cache_dir: str | Path | None = None,
    workers: int = 1,
    progress: Progress | None = None,
    overwrite: bool = False,
    evaluate: bool = True,
    setup_cache: str | Path | None = None,
) -> dict[str, Any]:
    """Augment a sequence into ``out_folder`` (OSDaR23 layout + metrics.json).

    Parameters
    ----------
    seq_folder : the input sequence.
    spec : what to add and how.
    out_folder : the output sequence folder (its name is the sequence name).
    prepared : a PreparedSequence; None runs (or reuses from ``cache_dir``) the
        preparation with ``spec.strategy`` and ``spec.clicks``.
    workers : processes for the frames (1: in this process).
    progress : ``progress(done, total)`` in frames.
    setup_cache : folder of cached camera render setups (default
        :func:`default_setup_cache`).

    Returns
    -------
    The metrics (also written to ``out_folder/metrics.json``).

    Raises
    ------
    AugmentError, PlacementError : the spec cannot be honoured (message says why).
    """
    t0 = time.perf_counter()
    out_folder = Path(out_folder)
    if out_folder.exists() and not overwrite:
        raise FileExistsError(f"{out_folder}: output sequence already exists")
    setup_cache = default_setup_cache() if setup_cache is None else Path(setup_cache)
    cams = _spec_cameras(seq_folder, spec)
    pool = None
    if workers > 1:  # this process is one of the workers
        pool = start_pool(workers - 1, cams, spec.render.antialias, setup_cache)
    # this process's render setups (~80 MB of remap for a 12 MP camera) read beside the
    # preparation and the plan: they are needed only when it renders its first frame
    loader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="render-setups")
    setups = loader.submit(lambda: [load_render_setup(cam, setup_cache) for cam in cams])
    loader.shutdown(wait=False)
    scratch = out_folder.with_name(out_folder.name + ".chunks")
    extra: dict[str, float] = {}
    try:
        if prepared is None:
            tic = time.perf_counter()
            prepared = _prepare(seq_folder, spec, cache_dir)
            extra["prepare"] = time.perf_counter() - tic
        # with a pool, the lidar noise's key frames are measured by this process while
        # the children start on the first frames (run_frames), not before them
        plan = plan_augmentation(seq_folder, spec, prepared, measure_noise=pool is None)
        if prepared.calibration is not None:
            plan.info["calibration"] = prepared.calibration.summary()
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True)
        if plan.lidar_noise_spheres:
            (scratch / ".lidar_noise").mkdir()
            plan.lidar_noise_dir = str(scratch / ".lidar_noise")
        tic = time.perf_counter()
        setups.result()
        chunks = run_frames(plan, scratch, pool, progress, evaluate=evaluate)
        extra["frames_total_wall"] = time.perf_counter() - tic
        extra["job_before_finish"] = time.perf_counter() - t0
        metrics = finish_augmentation(
            plan, chunks, out_folder, overwrite=overwrite, evaluate=evaluate, extra_timings=extra
        )
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        shutil.rmtree(scratch, ignore_errors=True)
    total = time.perf_counter() - t0
    metrics["timings_s"]["total"] = total
    (out_folder / METRICS_FILE).write_text(json.dumps(jsonable(metrics), indent=1))
    log.info("augmented %s -> %s in %.1f s", seq_folder, out_folder, total)
    return metrics


def _prepare(seq_folder: str | Path, spec: AugmentSpec, cache_dir: str | Path | None) -> Any:

    clicks = None if spec.clicks is None else Clicks.from_json(spec.clicks)
    config = PrepareConfig(strategy=spec.strategy)
    return prepare(seq_folder, config, clicks=clicks, cache_dir=cache_dir)


__all__ = ["AugmentError", "PlacementError", "augment"]
