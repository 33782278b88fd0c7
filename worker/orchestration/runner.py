"""The job's stages as plain functions: what the Celery tasks call, and what runs inline.

One job = one recipe (:func:`run_job_inline` reads it top to bottom)::

    start_job        count the delivery, start attempt n (poison jobs stop here)
    fetch_sequence   the sequence folder on this machine (shared path, or from the store)
    prepare_for_job  poses, registered cloud, tracks, scene (cached per sequence + config)
    augment_chunk    per chunk of frames: render, composite, lidar, annotations   [*]
    finish_job       untouched files, labels, augmentation metrics                [*]
    evaluate_job     RPE / jitter per camera (and true errors on synthetic data)
    package_job      archive: output sequence + metrics.json + report + previews
    publish_job      upload under an attempt-scoped key, then ONE conditional row update

[*] the chunks of one job can run on several workers at once. Each records its result
on the job's row; the one that completes the last chunk sends ``finish``, which reads
the results from there (``chunk_join.py``: the join in our database, not a chord).

Every stage runs inside :func:`_stage`: it holds the stage's lease while it runs (taken,
renewed by a heartbeat thread, released: ``lease.py``; the reaper re-queues a job whose
leases expired), checks that the attempt is still current and not cancelled, counts the
stage's deliveries (a stage that keeps killing its worker fails the job), shows the stage
on the job, times it, and turns errors into a FAILED job with a readable reason
(:class:`~worker.orchestration.state.JobFailed`) and cancellations into CANCELLED (partial
outputs removed). A lost database connection is not the job's error: it is raised as it
is and the task gives the stage back to the broker (``tasks.py``). Stages hold no DB
session while they compute.

Each stage can run on another machine than the previous one: it only needs the job id
and the attempt; local inputs (the fetched sequence, the prepared artifact, the archive)
are re-created from the store or the cache when missing.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tarfile
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from sqlalchemy import select

from osdar_platform.archive_safety import ArchiveLimits, UnsafeArchive, extract_archive
from osdar_platform.db import session_scope
from osdar_platform.models import Asset, Job, JobState, Sequence
from osdar_platform.retry import RetryingStore
from osdar_platform.settings import Settings, get_settings
from osdar_platform.store import ObjectStore, StoreError, store_from_url
from service.schemas import spec_asset_ids
from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import ChunkResult, augment_frames
from worker.augmentation.placement import PlacementError
from worker.augmentation.plan import AugmentError, Plan, plan_augmentation
from worker.augmentation.records import (
    RecordFormatError,
    dump_chunk,
    dump_plan,
    load_chunk,
    read_plan,
)
from worker.augmentation.spec import AugmentSpec, MeshFile
from worker.evaluation.object_error import measure_chunk
from worker.orchestration import chunk_join, lease, state
from worker.orchestration.lease import database_unreachable
from worker.orchestration.shared_results import rpe_plot, sequence_evaluation
from worker.orchestration.state import (
    POISON_REASON,
    JobCancelled,
    JobFailed,
    JobStop,
    JobSuperseded,
)
from worker.osdar.errors import SequenceError
from worker.osdar.sequence import find_labels_file
from worker.packaging import build_archive, make_previews
from worker.preparation.artifact import PreparedSequence, key_lock
from worker.preparation.calibration_point import Clicks, ClicksError
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import PreparationError, prepare

log = logging.getLogger(__name__)

ARCHIVE_NAME = "archive.tar.gz"
#: Exit code of the test-only crash hook (a worker process killed mid-task).
TEST_CRASH_EXIT_CODE = 70


# ---------------------------------------------------------------------------- context
@dataclass
class JobRun:
    """One attempt of one job on this machine: ids, settings, store, local folders."""

    job_id: str
    attempt: int
    settings: Settings
    _info: dict[str, Any] | None = field(default=None, repr=False)
    _store: ObjectStore | None = field(default=None, repr=False)

    @property
    def store(self) -> ObjectStore:
        """The object store, every call retried with backoff (osdar_platform/retry.py)."""
        if self._store is None:
            s = self.settings
            self._store = RetryingStore(
                store_from_url(str(s.store_url), s),
                retries=s.store_retries,
                base=s.store_retry_base_s,
                cap=s.store_retry_max_s,
                budget_s=s.store_retry_budget_s,
                on_retry=self._store_retry,
            )
        return self._store

    def _store_retry(self, op: str, key: str, n: int, delay: float, exc: BaseException) -> None:
        """Each store retry is a job event (the figures of scripts/reliability/)."""
        data = {"op": op, "key": key, "retry": n, "delay_s": round(delay, 3)}
        state.record_event(self.job_id, "store_retry", self.attempt, str(exc)[:500], data,
                           settings=self.settings)  # fmt: skip

    @property
    def workdir(self) -> Path:
        """Local scratch of this attempt (removed on success, failure and cancel)."""
        return Path(self.settings.cache_dir) / "jobs" / self.job_id / f"attempt-{self.attempt}"

    @property
    def prefix(self) -> str:
        """Store prefix of this attempt's objects."""
        return f"jobs/{self.job_id}/attempt-{self.attempt}/"

    @property
    def previews_prefix(self) -> str:
        return f"jobs/{self.job_id}/previews/attempt-{self.attempt}/"

    @property
    def info(self) -> dict[str, Any]:
        """The job's spec and its sequence's row (read once per run, short session)."""
        if self._info is None:
            with session_scope(self.settings) as s:
                job = s.get(Job, self.job_id)
                if job is None:
                    raise JobSuperseded(f"job {self.job_id} does not exist")
                seq = s.get(Sequence, job.sequence_id) if job.sequence_id else None
                self._info = {
                    "owner_id": job.owner_id,
                    "spec": dict(job.spec or {}),
                    "progress_total": job.progress_total,
                    "sequence": None
                    if seq is None
                    else {
                        "id": seq.id,
                        "name": seq.name,
                        "path": seq.path,
                        "content_key": seq.content_key,
                        "validation": dict(seq.validation or {}),
                    },
                }
        return self._info

    @property
    def spec(self) -> dict[str, Any]:
        spec: dict[str, Any] = self.info["spec"]
        return spec


def _run(job_id: str, attempt: int | None, settings: Settings | None) -> JobRun:
    settings = settings or get_settings()
    if attempt is None:
        attempt = state.current_attempt(job_id, settings=settings)
    return JobRun(job_id, attempt, settings)


# ---------------------------------------------------------------------------- stages
class StageError(Exception):
    """A problem of the job's input or spec, with a message for the user."""


def describe_error(stage: str, exc: BaseException) -> str:
    """A readable failure reason: the user's problem said plainly, ours named as such."""

    name = type(exc).__name__
    if name == "SoftTimeLimitExceeded":
        return f"{stage}: the job exceeded its time limit"
    user_errors: tuple[type[BaseException], ...] = (
        StageError,
        SequenceError,
        UnsafeArchive,
        StoreError,
    )
    user_errors += (PreparationError, ClicksError, AugmentError, PlacementError, RecordFormatError)
    if isinstance(exc, user_errors):
        return f"{stage}: {exc}"
    return f"{stage}: internal error ({name}: {exc})"


def _test_hook(run: JobRun, stage: str) -> None:
    """Test-only spec flags (``spec["_test"]``), honoured only in environment "test".

    ``crash_in``: the worker process exits at once in that stage (a poison input);
    ``fail_in``: the stage raises; ``terminated_in``: the stage is hit by the pool's
    termination inside an import; ``sleep_in``: {stage: seconds} before the stage's work.
    """
    if run.settings.environment != "test":
        return
    hooks = run.spec.get("_test")
    if not isinstance(hooks, dict):
        return
    if hooks.get("crash_in") == stage:
        log.error("test hook: killing this worker process in stage %s", stage)
        os._exit(TEST_CRASH_EXIT_CODE)
    if hooks.get("fail_in") == stage:
        raise RuntimeError(f"test hook: failure in {stage}")
    if hooks.get("terminated_in") == stage:
        # what billiard's SIGTERM handler does to a task caught inside an import
        try:
            raise SystemExit(-241)
        except SystemExit as exc:
            raise ImportError("initialization failed") from exc
    delay = (hooks.get("sleep_in") or {}).get(stage)
    if delay:
        time.sleep(float(delay))


def cleanup_attempt(run: JobRun, *, keep: frozenset[str] = frozenset()) -> None:
    """Remove this attempt's local scratch and its store objects (except ``keep``)."""
    shutil.rmtree(run.workdir, ignore_errors=True)
    for prefix in (run.prefix, run.previews_prefix):
        try:
            for key in run.store.list(prefix):
                if key not in keep:
                    run.store.delete(key)
        except Exception as exc:  # the row is what users see; orphans are only space
            log.warning("job %s: could not remove %s*: %s", run.job_id, prefix, exc)


@contextmanager
def _stage(
    run: JobRun,
    name: str,
    *,
    count_delivery: bool = True,
    admit: Callable[[], bool] | None = None,
) -> Iterator[None]:
    """Guard, show, time one stage; map its outcome onto the job (module docstring).

    ``admit``: asked once the lease is held, before anything else; False stops the stage
    as superseded (a stale duplicate ``finish``: ``chunk_join.admit_finish``).
    """
    s = run.settings
    with lease.held(run.job_id, run.attempt, name, settings=s):
        if admit is not None and not admit():
            raise JobSuperseded(f"job {run.job_id}: {name} of attempt {run.attempt} stale")
        with _outcome(run, name, count_delivery=count_delivery):
            yield


@contextmanager
def _outcome(run: JobRun, name: str, *, count_delivery: bool) -> Iterator[None]:
    """The body of :func:`_stage` inside the stage's lease."""
    s = run.settings
    try:
        state.check_attempt(run.job_id, run.attempt, settings=s)
        if count_delivery:
            n = state.count_stage_delivery(run.job_id, run.attempt, name, settings=s)
            if n > s.max_deliveries:
                reason = f"{POISON_REASON} (stage {name} delivered {n} times)"
                state.mark_failed(run.job_id, reason, settings=s, attempt=run.attempt)
                cleanup_attempt(run)
                raise JobFailed(reason)
        state.set_stage(run.job_id, run.attempt, name, settings=s)
        _test_hook(run, name)
        t0 = time.perf_counter()
        yield
        state.record_timing(run.job_id, run.attempt, name, time.perf_counter() - t0, settings=s)
    except (JobSuperseded, JobFailed):
        raise
    except JobCancelled:
        cleanup_attempt(run)
        state.mark_cancelled(run.job_id, settings=s, attempt=run.attempt)
        log.info("job %s cancelled in stage %s", run.job_id, name)
        raise
    except Exception as exc:
        stop = _termination(exc)
        if stop is not None:
            # Not the job's fault: the pool is terminating this process (Celery does so
            # when the broker connection drops under late acks) and the exit surfaced as
            # another error, e.g. an ImportError from a half-run import. Failing the job
            # would be wrong, and this process may hold a half-initialised module: let it
            # exit; the message is redelivered or the reaper re-queues the job.
            log.warning("job %s: process terminated in stage %s", run.job_id, name)
            raise stop from exc
        if database_unreachable(exc):
            # Not the job's fault either: the stage goes back to the broker (tasks.py) and
            # runs again when the database is back; failing the job needs it anyway.
            log.warning("job %s: database unreachable in stage %s: %s", run.job_id, name, exc)
            raise
        reason = describe_error(name, exc)
        log.exception("job %s attempt %d failed in %s", run.job_id, run.attempt, name)
        state.mark_failed(run.job_id, reason, settings=s, attempt=run.attempt)
        cleanup_attempt(run)
        raise JobFailed(reason) from exc


def _termination(exc: BaseException) -> BaseException | None:
    """The SystemExit or KeyboardInterrupt behind ``exc`` (its causes and contexts), if any."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, (SystemExit, KeyboardInterrupt)):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


# ---------------------------------------------------------------------------- start
def start_job(job_id: str, *, settings: Settings | None = None) -> int:
    """Count this delivery and start a new attempt; returns its number (see state.py)."""
    settings = settings or get_settings()
    attempt = state.mark_running(job_id, settings=settings)
    _test_hook(JobRun(job_id, attempt, settings), "run_job")
    return attempt


def job_frames(run: JobRun, frame_indices: list[int] | None = None) -> list[int]:
    """The frames the job augments: the sequence's, within ``spec.frame_range``."""
    if frame_indices is None:
        seq = run.info["sequence"] or {}
        frame_indices = list((seq.get("validation") or {}).get("frame_indices") or [])
    rng = run.spec.get("frame_range")
    if rng is None:
        return sorted(frame_indices)
    lo, hi = int(rng[0]), int(rng[1])
    return sorted(f for f in frame_indices if lo <= f <= hi)


def plan_chunks(
    job_id: str, *, attempt: int | None = None, settings: Settings | None = None
) -> list[list[int]]:
    """The job's frames in chunks of at most ``settings.frames_per_chunk``
    (:func:`split_frames`); their number is recorded for the join before ``finish``
    (``chunk_join.plan``)."""
    run = _run(job_id, attempt, settings)
    chunks = split_frames(job_frames(run), run.settings.frames_per_chunk)
    chunk_join.plan(run.job_id, run.attempt, len(chunks), settings=run.settings)
    return chunks


def split_frames(frames: list[int], per_chunk: int) -> list[list[int]]:
    """``frames`` in as few chunks as ``per_chunk`` allows, dealt out in turn (chunk k
    takes every n-th frame from the k-th): the chunks differ by at most one frame and
    take alike of the frames where the object is near and costly, so that chunks that
    run side by side end together (40 frames at 25 a chunk were 25 + 15 frames, and the
    longer chunk ran alone at the end of every job). The first chunk starts with the
    first frame."""
    n = -(-len(frames) // per_chunk)
    return [frames[k::n] for k in range(n)]


# ---------------------------------------------------------------------------- fetch
def _local_sequence(run: JobRun) -> Path:
    """The sequence folder on this machine: its registered path, or its upload fetched."""

    seq = run.info["sequence"]
    if seq is None:
        raise StageError("the job's sequence was deleted")
    return sequence_folder(seq, run.settings, lambda: run.store)


def sequence_folder(
    seq: dict[str, Any], settings: Settings, store: Callable[[], ObjectStore]
) -> Path:
    """A sequence row's folder on this machine (``seq``: id, path, content_key): its
    registered path, or its upload fetched from ``store()`` once (cached per sequence).
    A job's fetch and a campaign's expansion both call this."""
    folder = Path(seq["path"])
    if folder.is_dir():
        return folder
    if not seq["content_key"]:
        raise StageError(f"sequence folder {folder} is not readable on this worker")

    base = Path(settings.cache_dir) / "sequences" / str(seq["id"])
    marker = base / "root.txt"
    with key_lock(base.parent, f"sequence-{seq['id']}"):
        if marker.is_file():
            return base / marker.read_text().strip()
        shutil.rmtree(base, ignore_errors=True)
        base.mkdir(parents=True)
        archive = base / "source.archive"
        store().get_file(seq["content_key"], archive)
        result = extract_archive(archive, base / "tree", ArchiveLimits.from_settings(settings))
        archive.unlink()
        root = result.root
        find_labels_file(root)  # a clear error now rather than in preparation
        marker.write_text(root.relative_to(base).as_posix())
        return root


def fetch_sequence(
    job_id: str, *, attempt: int | None = None, settings: Settings | None = None
) -> Path:
    """Make the job's sequence readable here (cached per sequence); returns its folder."""
    run = _run(job_id, attempt, settings)
    with _stage(run, "fetch"):
        return _local_sequence(run)


# ---------------------------------------------------------------------------- prepare
def _prepare(run: JobRun, progress: Any = None) -> PreparedSequence:
    """The prepared sequence of the job (from the per-key cache when it is there)."""

    spec = run.spec
    config = PrepareConfig(strategy=spec.get("strategy") or "auto")
    clicks = None
    if spec.get("clicks"):
        # the landmark's name is part of the cache key: the augmentation's own name for it
        clicks = Clicks.from_json({"landmark": "job", "clicks": spec["clicks"]}, "spec.clicks")
    return prepare(
        _local_sequence(run),
        config,
        clicks=clicks,
        cache_dir=run.settings.prepared_cache_dir,
        progress=progress,
    )


def prepare_for_job(
    job_id: str, *, attempt: int | None = None, settings: Settings | None = None
) -> PreparedSequence:
    """Preparation of the job's sequence (shared by every job on it) and the job's
    augmentation plan (:func:`_plan`); returns the preparation."""
    run = _run(job_id, attempt, settings)
    with _stage(run, "prepare"):

        def progress(sub: str, done: int, total: int) -> None:
            state.check_attempt(run.job_id, run.attempt, settings=run.settings)
            state.set_stage(run.job_id, run.attempt, f"prepare: {sub}", settings=run.settings)

        prepared = _prepare(run, progress)
        s = prepared.summary
        state.merge_metrics(
            run.job_id,
            run.attempt,
            {
                "preparation": {
                    "key": prepared.key,
                    "reused": bool(s.get("reused")),
                    "strategy": prepared.strategy,
                    "seconds": s.get("total_seconds"),
                    "warnings": len(s.get("warnings", [])),
                }
            },
            settings=run.settings,
        )
        # The plan too: every chunk reads it, so no chunk of the job sleeps while another
        # computes it (meanwhile the other worker processes take other jobs' stages).
        state.set_stage(run.job_id, run.attempt, "prepare: plan", settings=run.settings)
        _plan(run, prepared)
        return prepared


# ---------------------------------------------------------------------------- augment
def _augment_spec(run: JobRun) -> AugmentSpec:
    """The augmentation's spec from the job spec: every object's uploaded mesh (the one
    ``object`` or any of ``objects``) read from the store, each asset the job owner's."""

    spec = run.spec
    assets: dict[str, MeshFile] = {}
    for where, asset_id in spec_asset_ids(spec):
        if asset_id in assets:
            continue
        with session_scope(run.settings) as s:
            asset = s.get(Asset, asset_id)
            if asset is not None and asset.owner_id == run.info["owner_id"]:
                key, file_type = asset.store_key, asset.file_type
            else:  # deleted since the submission, or never the owner's
                raise StageError(f"{where}: asset {asset_id} was deleted")
        assets[asset_id] = (b"".join(run.store.open_read(key)), file_type)
    return AugmentSpec.from_job_spec(spec, assets=assets)


def _plan(run: JobRun, prepared: PreparedSequence | None = None) -> Plan:
    """The augmentation plan of this attempt: computed once, shared through the store.

    Every chunk needs it; the first worker to need it computes and uploads it, the others
    download it (a race between machines only computes the same plan twice). The chunks
    of a job running at once on one machine wait for each other here: one computes, the
    others read its file (with 2 worker processes both chunks of a variant start together,
    and both computed the plan).
    """
    local = run.workdir / "plan.npz"
    if not local.is_file():
        local.parent.mkdir(parents=True, exist_ok=True)
        with key_lock(run.workdir, "plan"):
            if not local.is_file():
                plan = _make_plan(run, local, prepared)
                if plan is not None:
                    return plan
    return read_plan(local)  # a typed record, validated as it is read


def _make_plan(run: JobRun, local: Path, prepared: PreparedSequence | None) -> Plan | None:
    """The plan into ``local``: from the store (None returned), or computed from
    ``prepared`` (read from the cache when None) and uploaded (returned)."""
    key = f"{run.prefix}plan.npz"
    # a worker killed half-way leaves only its private temporary file: the shared file
    # appears by an atomic rename
    tmp = local.with_name(f"plan.{os.getpid()}.{uuid.uuid4().hex}.part")
    if run.store.exists(key):
        run.store.get_file(key, tmp)
        tmp.replace(local)
        return None
    if prepared is None:
        prepared = _prepare(run)
    plan = plan_augmentation(_local_sequence(run), _augment_spec(run), prepared)
    if prepared.calibration is not None:
        plan.info["calibration"] = prepared.calibration.summary()
    tmp.write_bytes(dump_plan(plan))
    run.store.put_file(key, tmp)
    tmp.replace(local)
    return plan


def _chunk_dir(run: JobRun, index: int) -> Path:
    return run.workdir / "chunks" / f"{index:04d}"


def _chunk_done(run: JobRun, index: int) -> Path:
    """Marker: the chunk's local folder is whole (written here, or fetched whole)."""
    return run.workdir / "chunks" / f"{index:04d}.done"


def augment_chunk(
    job_id: str,
    index: int,
    frames: list[int],
    *,
    attempt: int | None = None,
    settings: Settings | None = None,
) -> dict[str, Any]:
    """Augment one chunk of frames (any worker); its files and records go to the store,
    and the chunk is recorded done on the job's row (``chunk_join.complete_chunk``).

    Returns ``{"index", "frames", "files", "records"}``: store keys (JSON). A chunk
    already recorded done (delivered again) returns its record without redoing the work.
    """
    run = _run(job_id, attempt, settings)
    done = chunk_join.chunk_result(run.job_id, run.attempt, index, settings=run.settings)
    if done is not None:
        log.info("job %s attempt %d: chunk %d was done already", job_id, run.attempt, index)
        return dict(done)
    with _stage(run, f"augment[{index}]"):
        state.set_stage(run.job_id, run.attempt, "augment", settings=run.settings)
        plan = _plan(run)
        out = _chunk_dir(run, index)
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        result: ChunkResult | None = None
        for f in frames:  # one frame at a time: progress, and a cancel stops here
            state.check_attempt(run.job_id, run.attempt, settings=run.settings)
            part = augment_frames(plan, [f], out)
            measure_chunk(plan, part)  # the finish only sums the errors up
            if result is None:
                result = part
            else:
                result.files += part.files
                result.frames += part.frames
                result.seconds += part.seconds
                result.object_errors.update(part.object_errors)
            state.add_progress(run.job_id, run.attempt, 1, settings=run.settings)
        files_key = f"{run.prefix}chunks/{index:04d}.tar"
        records_key = f"{run.prefix}chunks/{index:04d}.npz"
        tar_path = out.with_suffix(".tar")
        # a new file, never one rewritten in place: the store may hold a link to the old
        tar_path.unlink(missing_ok=True)
        with tarfile.open(tar_path, "w") as tar:
            tar.add(out, arcname=".")
        run.store.put_file(files_key, tar_path, consume=True)
        tar_path.unlink(missing_ok=True)
        assert result is not None  # a chunk has at least one frame
        run.store.put_bytes(records_key, dump_chunk(result))
        _chunk_done(run, index).write_text("ok")
        record = {"index": index, "frames": list(frames), "files": files_key,
                  "records": records_key}  # fmt: skip
        chunk_join.complete_chunk(run.job_id, run.attempt, index, record, settings=run.settings)
        return record


def _output_folder(run: JobRun) -> Path:
    name: str = (run.info["sequence"] or {}).get("name", "sequence")
    return run.workdir / "output" / name


def _chunk_results(run: JobRun, chunks: list[dict[str, Any]]) -> list[ChunkResult]:
    """Every chunk's records, with its files on this machine (downloaded if need be)."""

    out = []
    for c in sorted(chunks, key=lambda c: c["index"]):
        folder = _chunk_dir(run, c["index"])
        if not _chunk_done(run, c["index"]).is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.parent.mkdir(parents=True, exist_ok=True)
            tar_path = folder.with_suffix(".tar")
            run.store.get_file(c["files"], tar_path)
            extract_archive(tar_path, folder, ArchiveLimits.from_settings(run.settings))
            tar_path.unlink(missing_ok=True)
        result = load_chunk(b"".join(run.store.open_read(c["records"])), c["records"])
        result.root = str(folder)
        out.append(result)
    return out


def _assemble_output(run: JobRun, chunks: list[dict[str, Any]]) -> tuple[Path, dict[str, Any]]:
    """The complete output sequence from the chunks (the augmentation's finish)."""
    out = _output_folder(run)
    shutil.rmtree(out.parent, ignore_errors=True)
    out.parent.mkdir(parents=True)
    plan = _plan(run)
    results = _chunk_results(run, chunks)
    # finish_augmentation MOVES the chunks' files into the output: from here on the local
    # chunk folders are no longer whole, so a finish killed half-way and run again must
    # fetch them from the store instead of trusting them.
    for c in chunks:
        _chunk_done(run, c["index"]).unlink(missing_ok=True)
    metrics = finish_augmentation(plan, results, out, overwrite=True)
    shutil.rmtree(run.workdir / "chunks", ignore_errors=True)
    (out.parent / ".complete").write_text("ok")
    return out, json.loads(json.dumps(metrics, default=str))


def finish_job(
    job_id: str,
    chunks: list[dict[str, Any]] | None = None,
    *,
    token: str | None = None,
    attempt: int | None = None,
    settings: Settings | None = None,
) -> dict[str, Any]:
    """After every chunk: the complete output sequence and the augmentation metrics.

    ``chunks``: the chunks' results (default: as recorded on the job's row). ``token``:
    the finish token the message carries (``chunk_join.claim_finish``); a stale one stops
    here (:class:`JobSuperseded`) before taking the stage's lease or counting a delivery.
    """
    run = _run(job_id, attempt, settings)
    s = run.settings
    admit: Callable[[], bool] | None = None
    if token is not None:
        if not chunk_join.finish_token_current(run.job_id, run.attempt, token, settings=s):
            raise JobSuperseded(f"job {job_id}: finish of attempt {run.attempt} stale")
        admit = partial(chunk_join.admit_finish, run.job_id, run.attempt, token, settings=s)
    with _stage(run, "finish", admit=admit):
        if chunks is None:
            chunks = chunk_join.chunk_results(run.job_id, run.attempt, settings=s)
        if not chunks:
            raise JobSuperseded(f"job {job_id}: attempt {run.attempt} has no chunk done")
        index = json.dumps(sorted(chunks, key=lambda c: c["index"])).encode()
        run.store.put_bytes(f"{run.prefix}chunks/index.json", index)
        _, metrics = _assemble_output(run, chunks)
        update = {"augmentation": metrics}
        state.merge_metrics(run.job_id, run.attempt, update, settings=run.settings)
        return {"frames": len(metrics.get("frames") or {})}


def output_sequence(run: JobRun) -> Path:
    """The folder to package: the augmented sequence (rebuilt here when need be)."""
    out = _output_folder(run)
    if (out.parent / ".complete").is_file():
        return out
    # finished on another worker: rebuild it here from the chunks in the store
    index = b"".join(run.store.open_read(f"{run.prefix}chunks/index.json"))
    out, _ = _assemble_output(run, json.loads(index))
    return out


# ---------------------------------------------------------------------------- evaluate
def evaluate_job(
    job_id: str, *, attempt: int | None = None, settings: Settings | None = None
) -> dict[str, Any]:
    """RPE / jitter of the job's poses (and true errors on synthetic data) -> metrics."""

    run = _run(job_id, attempt, settings)
    with _stage(run, "evaluate"):
        seq_folder = _local_sequence(run)
        prepared = _prepare(run)
        cameras = list(run.spec.get("cameras") or [])
        metrics, series = sequence_evaluation(seq_folder, prepared, cameras,
                                              cache_dir=run.settings.cache_dir)  # fmt: skip
        seq = run.info["sequence"] or {}
        update = {
            "sequence": {
                "id": seq.get("id"),
                "name": seq.get("name"),
                "frames": len(job_frames(run)),
            },
            "evaluation": {**metrics, "per_frame": series},
        }
        state.merge_metrics(run.job_id, run.attempt, update, settings=run.settings)
        return update


# ---------------------------------------------------------------------------- package
def _archive_path(run: JobRun) -> Path:
    return run.workdir / ARCHIVE_NAME


def _report(run: JobRun, metrics: dict[str, Any]) -> dict[str, Path]:
    """metrics.json, the RPE/jitter plot, previews, preparation summary -> {arcname: file}."""

    report = run.workdir / "report"
    shutil.rmtree(report, ignore_errors=True)
    report.mkdir(parents=True)
    files: dict[str, Path] = {}
    (report / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
    files["metrics.json"] = report / "metrics.json"
    series = (metrics.get("evaluation") or {}).get("per_frame") or {}
    title = f"RPE and jitter, strategy {(metrics.get('evaluation') or {}).get('strategy')}"
    plot = rpe_plot(series, report / "previews" / "rpe_jitter.png", title,
                    cache_dir=run.settings.cache_dir)  # fmt: skip
    if plot is not None:
        files["report/rpe_jitter.png"] = plot
    out = output_sequence(run)
    cameras = list(run.spec.get("cameras") or [])
    for p in make_previews(out, cameras, report / "previews", lidar=bool(run.spec.get("lidar"))):
        files[f"report/previews/{p.name}"] = p
    prep_summary = run.settings.prepared_cache_dir
    key = (metrics.get("preparation") or {}).get("key")
    if key and (prep_summary / key / "summary.json").is_file():
        files["report/preparation.json"] = prep_summary / key / "summary.json"
    return files


def package_job(
    job_id: str, *, attempt: int | None = None, settings: Settings | None = None
) -> Path:
    """The archive of the job's output (OSDaR23 layout + metrics.json + report)."""
    run = _run(job_id, attempt, settings)
    with _stage(run, "package"):
        return _package(run)


def _package(run: JobRun) -> Path:

    metrics = state.get_metrics(run.job_id, settings=run.settings)
    extra = _report(run, metrics)
    return build_archive(output_sequence(run), _archive_path(run), extra=extra)


# ---------------------------------------------------------------------------- publish
def upload_and_publish(run: JobRun, archive: Path) -> str | None:
    """Upload under this attempt's keys, then the one conditional update that publishes.
    The store takes ``archive`` and the previews as they are (``consume``: a local store
    links them): they are only deleted afterwards, never rewritten in place.

    Returns the published key if this attempt's result is the job's result, else None
    (another attempt won: this attempt's objects are deleted).
    """
    key = f"{run.prefix}{ARCHIVE_NAME}"
    run.store.put_file(key, archive, consume=True)
    previews = []
    folder = run.workdir / "report" / "previews"
    for p in sorted(folder.glob("*.png")) if folder.is_dir() else []:
        pkey = f"{run.previews_prefix}{p.name}"
        run.store.put_file(pkey, p, consume=True)
        previews.append(pkey)
    won = state.publish_result(
        run.job_id, run.attempt, key, settings=run.settings, previews=previews
    )
    with session_scope(run.settings) as s:
        published = s.scalar(select(Job.result_key).where(Job.id == run.job_id))
    if won or published == key:
        _remove_orphans(run, keep={key, *previews})
        shutil.rmtree(run.workdir, ignore_errors=True)
        return key
    log.info("job %s attempt %d: another attempt published first", run.job_id, run.attempt)
    cleanup_attempt(run)
    return None


def _remove_orphans(run: JobRun, keep: set[str]) -> None:
    """Every object of the job but the published ones (other attempts, chunk files)."""
    try:
        for key in run.store.list(f"jobs/{run.job_id}/"):
            if key not in keep:
                run.store.delete(key)
    except Exception as exc:
        log.warning("job %s: orphan cleanup failed: %s", run.job_id, exc)


def publish_job(
    job_id: str,
    archive: str | Path | None = None,
    *,
    attempt: int | None = None,
    settings: Settings | None = None,
) -> str | None:
    """Publish the archive (re-made here when it is on another machine); returns its key."""
    run = _run(job_id, attempt, settings)
    with _stage(run, "publish"):
        path = Path(archive) if archive else None
        if path is None or not path.is_file():
            path = _package(run)
        return upload_and_publish(run, path)


# ---------------------------------------------------------------------------- inline
def run_job_inline(job_id: str, *, settings: Settings | None = None) -> JobState:
    """The whole job in this process, without Celery (CLI, tests); returns its end state."""
    settings = settings or get_settings()
    try:
        attempt = start_job(job_id, settings=settings)
        kw: dict[str, Any] = {"attempt": attempt, "settings": settings}
        fetch_sequence(job_id, **kw)
        prepare_for_job(job_id, **kw)
        for i, frames in enumerate(plan_chunks(job_id, **kw)):
            augment_chunk(job_id, i, frames, **kw)
        token = chunk_join.claim_finish(job_id, attempt, settings=settings)
        if token is None:  # the attempt was superseded meanwhile
            raise JobSuperseded(f"job {job_id}: attempt {attempt} has nothing to finish")
        finish_job(job_id, token=token, **kw)
        evaluate_job(job_id, **kw)
        archive = package_job(job_id, **kw)
        publish_job(job_id, archive, **kw)
    except JobStop as stop:
        log.info("job %s stopped: %s", job_id, stop)
    with session_scope(settings) as s:
        job_state = s.scalar(select(Job.state).where(Job.id == job_id))
    if job_state is None:
        raise ValueError(f"job {job_id}: no such job")
    return JobState(job_state)


__all__ = [
    "JobRun",
    "augment_chunk",
    "cleanup_attempt",
    "evaluate_job",
    "fetch_sequence",
    "finish_job",
    "package_job",
    "plan_chunks",
    "prepare_for_job",
    "publish_job",
    "run_job_inline",
    "sequence_folder",
    "start_job",
    "upload_and_publish",
]
