"""A campaign run embedded (no server): ``osdar-ar campaign run SPEC``.

The recipe (:func:`run_campaign` reads it top to bottom)::

    load_campaign        the spec file validated (errors name the file and the field)
    sequence_folders     each sequence entry's folder (the CLI needs ``path``)
    check_runnable       what an embedded run cannot make is refused up front
                         (uploaded assets, which live in the service's store)
    prepare_sequences    ONE preparation per sequence (the prepared cache), shared by all
                         of its variants
    expand_campaign      the deterministic expansion with resolved positions
    run_variant          per variant: the augmentation library (worker.augmentation.augment,
                         the same code as ``osdar-ar augment`` and a service job's chunks),
                         the report and the archive, the contact frame, the record
    write_manifest       manifest.json + manifest.csv (worker.campaign.manifest)
    write_contact_sheet  contact_sheet.png (worker.campaign.contact_sheet)

The output folder::

    campaign.json            the validated spec and where it came from
    variants.json            the expansion (canonical JSON: same spec, same bytes)
    archives/<vid>_<sequence>_<class>.tar.gz   one archive per variant, as a job's
    records/<vid>.json       what a finished (or failed) variant produced
    thumbs/<vid>.png         its contact frame
    manifest.json, manifest.csv, contact_sheet.png

Resuming: a variant is complete when its record says ``done`` for the same variant key
and its archive is there with the recorded size. Archives and records are written under
a temporary name and renamed into place, so an interrupted run leaves nothing half
written that a re-run would trust; the re-run skips the complete variants and makes the
others.

The evaluation (paper RPE / jitter per camera, :func:`~worker.evaluation.evaluate.
evaluate_sequence`) depends on the sequence's preparation and the cameras only, not on
the object: it is computed once per sequence and written into every variant's
``metrics.json``, as a service job writes it.

Several objects in one variant (``objects_per_sequence`` > 1) are one augmentation with
``objects`` (:class:`~worker.augmentation.spec.AugmentSpec`): each object annotated, the
objects hiding each other; the record's ``gauge`` is over all of them (intrudes when any
does), ``object_gauges`` has each one's. Moving obstacles carry their ``motion``.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from worker.augmentation.augment import augment
from worker.augmentation.placement import PlacementError
from worker.augmentation.plan import AugmentError
from worker.augmentation.spec import AugmentSpec
from worker.campaign.contact_sheet import contact_frame, write_contact_sheet, write_thumbnail
from worker.campaign.expand import expand_with_issues
from worker.campaign.manifest import manifest_rows, write_atomic, write_manifest
from worker.campaign.spec import CampaignSpec, spec_issues
from worker.campaign.variant import Variant, dump_variants
from worker.evaluation.evaluate import evaluate_sequence, plot_rpe_jitter
from worker.json_values import jsonable
from worker.osdar.errors import SequenceError
from worker.packaging import build_archive, make_previews
from worker.preparation.artifact import PreparedSequence, cached_folder, read_artifact
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import PreparationError, prepare

log = logging.getLogger(__name__)

VariantState = Literal["done", "failed", "pending"]

#: Called after each variant: (variant, its record, whether it was skipped as complete).
VariantDone = Callable[[Variant, "VariantRecord", bool], None]


class CampaignRunError(ValueError):
    """A campaign that cannot run as asked; the message names the file and the field."""


@dataclass
class VariantRecord:
    """What one variant produced (``records/<vid>.json``); paths relative to the output.

    gauge : the augmentation's gauge summary (intrusion frames, lateral distance to the
        envelope, distance along the track; worker/augmentation/gauge.py); over all
        objects of a several-object variant (:func:`combined_gauge`).
    object_gauges : each object's gauge summary (the variant's objects' order).
    quality : per camera, ``rpe_px_mean`` / ``jitter_px_mean`` (the paper's RPE and
        jitter, chosen strategy) and ``bound_px_median`` (median of the per-frame 90 %
        placement bound over the frames the object is visible in).
    contact : the contact frame: ``frame``, ``camera``, ``bbox`` [xc, yc, w, h] px (None:
        the object shows in no frame, the middle frame is used), ``thumb``.
    """

    variant: str
    key: str
    state: VariantState
    error: str | None = None
    archive: str | None = None
    archive_bytes: int | None = None
    seconds: float | None = None
    strategy: str | None = None
    annotated_frames: int | None = None
    visible_frames: dict[str, int] = field(default_factory=dict)
    gauge: dict[str, Any] | None = None
    object_gauges: list[dict[str, Any] | None] = field(default_factory=list)
    quality: dict[str, dict[str, float | None]] = field(default_factory=dict)
    contact: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return dict(jsonable(self.__dict__))

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> VariantRecord:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


@dataclass
class CampaignResult:
    """A run's outcome: the variants, their records (None: not run), the files written."""

    spec: CampaignSpec
    out_dir: Path
    variants: list[Variant]
    records: dict[str, VariantRecord | None]
    skipped: list[str]
    wall_s: float
    prepare_s: dict[str, float]
    evaluate_s: dict[str, float] = field(default_factory=dict)
    manifest_json: Path | None = None
    manifest_csv: Path | None = None
    contact_sheet: Path | None = None

    @property
    def failed(self) -> list[str]:
        return [v for v, r in self.records.items() if r is not None and r.state == "failed"]


# ---------------------------------------------------------------------------- the spec
def _format_issues(path: Path, issues: list[Any]) -> str:
    return "; ".join(f"{path}: {i.where}: {i.message}" for i in issues)


def load_campaign(path: str | Path) -> CampaignSpec:
    """The spec file (``.json`` as JSON, anything else as YAML), validated.

    Raises CampaignRunError naming the file and every invalid field
    (``spec.yaml: placements[0].zone: Input should be 'track', ...``).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise CampaignRunError(f"{path}: cannot read the campaign spec ({exc.strerror})") from exc
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
        msg = " ".join(str(exc).split())
        raise CampaignRunError(f"{path}: not valid {kind}: {msg}") from exc
    if not isinstance(data, dict):
        raise CampaignRunError(
            f"{path}: a campaign spec is a mapping (name, sequences, obstacles, ...)"
        )
    spec, issues = spec_issues(data)
    if spec is None:
        raise CampaignRunError(_format_issues(path, issues))
    return spec


def sequence_folders(
    spec: CampaignSpec, spec_path: str | Path, base: str | Path | None = None
) -> dict[str, Path]:
    """Each sequence entry's key -> its folder (relative paths from ``base``, default the
    current directory). Raises CampaignRunError naming the entry."""
    base = Path.cwd() if base is None else Path(base)
    out: dict[str, Path] = {}
    for i, entry in enumerate(spec.sequences):
        where = f"{spec_path}: sequences[{i}]"
        if entry.path is None:
            raise CampaignRunError(
                f"{where}: id {entry.id!r} names a sequence registered in the service; "
                "`campaign run` runs here and needs a folder: give `path`"
            )
        folder = Path(entry.path).expanduser()
        folder = folder if folder.is_absolute() else base / folder
        if not folder.is_dir():
            raise CampaignRunError(
                f"{where}.path: {entry.path!r} is not a folder ({folder}; relative paths are "
                "from the current directory); make a synthetic one with `osdar-ar synth`"
            )
        out[entry.key] = folder
    return out


def check_assets(spec: CampaignSpec, spec_path: str | Path) -> None:
    """Refuse uploaded assets: they live in the service's asset store, which an embedded
    run does not have."""
    for i, ob in enumerate(spec.obstacles):
        if ob.asset_id is not None:
            raise CampaignRunError(
                f"{spec_path}: obstacles[{i}]: asset_id {ob.asset_id!r} names a mesh uploaded "
                "to the service; `campaign run` has built-in obstacles only"
            )


def check_runnable(spec: CampaignSpec, spec_path: str | Path) -> None:
    """Refuse what an embedded run cannot make (module docstring): uploaded assets."""
    check_assets(spec, spec_path)


def prepare_config(spec: CampaignSpec) -> PrepareConfig:
    """The preparation every variant of the campaign uses (the spec's strategy)."""
    return PrepareConfig(strategy=spec.job.strategy)


def prepare_sequences(
    spec: CampaignSpec,
    folders: Mapping[str, Path],
    *,
    cache_dir: str | Path | None,
    spec_path: str | Path = "spec",
    on_prepared: Callable[[str, float, bool], None] | None = None,
) -> tuple[dict[str, PreparedSequence], dict[str, float]]:
    """ONE preparation per sequence (from ``cache_dir`` when it is there); returns the
    prepared sequences by key and the seconds each took. ``on_prepared(label, seconds,
    reused)`` after each. Raises CampaignRunError naming the entry."""
    config = prepare_config(spec)
    prepared: dict[str, PreparedSequence] = {}
    seconds: dict[str, float] = {}
    for i, entry in enumerate(spec.sequences):
        tic = time.perf_counter()
        try:
            got = prepare(folders[entry.key], config, cache_dir=cache_dir)
        except (SequenceError, PreparationError) as exc:
            raise CampaignRunError(
                f"{spec_path}: sequences[{i}] ({entry.label}): cannot prepare: {exc}"
            ) from exc
        reused = bool(got.summary.get("reused"))
        if cache_dir is not None and not reused:
            # expand on the cached artifact's numbers, as a resumed run will: a fresh
            # preparation and its stored copy differ in the last bits, which can move a
            # position rounded to the millimetre (same spec, same bytes)
            got = read_artifact(cached_folder(cache_dir, got.key))
            got.summary["reused"] = False
        prepared[entry.key] = got
        seconds[entry.key] = time.perf_counter() - tic
        log.info(
            "campaign %s: %s prepared in %.1f s (reused: %s)",
            spec.name,
            entry.label,
            seconds[entry.key],
            reused,
        )
        if on_prepared is not None:
            on_prepared(entry.label, seconds[entry.key], reused)
    return prepared, seconds


def expand_campaign(
    spec: CampaignSpec, prepared: Mapping[str, Any], spec_path: str | Path = "spec"
) -> tuple[list[Variant], list[str]]:
    """The variants and the expansion's warnings; CampaignRunError with every error."""
    variants, issues = expand_with_issues(spec, prepared)
    errors = [i for i in issues if i.level == "error"]
    if errors:
        raise CampaignRunError(_format_issues(Path(spec_path), errors))
    return variants, [str(i) for i in issues]


# ---------------------------------------------------------------------------- files
def write_json_atomic(path: Path, obj: Any) -> Path:
    return write_atomic(path, json.dumps(jsonable(obj), indent=1, sort_keys=True).encode())


def _slug(text: str) -> str:
    return re.sub(r"[^\w.+-]+", "_", text).strip("_") or "x"


def archive_name(variant: Variant) -> str:
    """``archives/<vid>_<sequence>_<class>.tar.gz`` (relative to the output folder)."""
    classes = "+".join(o.class_name for o in variant.objects)
    return f"archives/{variant.id}_{_slug(variant.sequence_label)}_{_slug(classes)}.tar.gz"


def record_path(out_dir: Path, variant: Variant) -> Path:
    return out_dir / "records" / f"{variant.id}.json"


def read_record(out_dir: Path, variant: Variant) -> VariantRecord | None:
    p = record_path(out_dir, variant)
    try:
        return VariantRecord.from_json(json.loads(p.read_text()))
    except (OSError, ValueError, TypeError):
        return None


def complete_record(out_dir: Path, variant: Variant) -> VariantRecord | None:
    """The variant's record when the variant is complete (module docstring), else None."""
    rec = read_record(out_dir, variant)
    if rec is None or rec.state != "done" or rec.key != variant.key or rec.archive is None:
        return None
    archive = out_dir / rec.archive
    if not archive.is_file() or archive.stat().st_size != rec.archive_bytes:
        return None
    return rec


def _forget(out_dir: Path, variant: Variant) -> None:
    """Before a variant is (re)made: its old record and, when the old archive had another
    name (the spec changed), that archive go; so does a half-written one (a killed run)."""
    old = read_record(out_dir, variant)
    record_path(out_dir, variant).unlink(missing_ok=True)
    if old is not None and old.archive and old.archive != archive_name(variant):
        (out_dir / old.archive).unlink(missing_ok=True)
    partial = out_dir / archive_name(variant)
    partial.with_name(partial.name + ".partial").unlink(missing_ok=True)


# ---------------------------------------------------------------------------- a variant
@dataclass
class SequenceContext:
    """What every variant on one sequence shares: its folder, its preparation, and its
    evaluation (computed on first use)."""

    folder: Path
    prepared: PreparedSequence
    cameras: list[str]
    work: Path
    evaluation_s: float | None = None
    _evaluation: tuple[dict[str, Any], dict[str, Any]] | None = None
    _plot: Path | None = None

    def evaluation(self) -> tuple[dict[str, Any], dict[str, Any]]:
        if self._evaluation is None:
            tic = time.perf_counter()
            self._evaluation = evaluate_sequence(self.folder, self.prepared, self.cameras)
            self.evaluation_s = time.perf_counter() - tic
            log.info("evaluated %s in %.1f s", self.folder.name, self.evaluation_s)
            metrics, series = self._evaluation
            title = f"RPE and jitter, strategy {metrics.get('strategy')}"
            self.work.mkdir(parents=True, exist_ok=True)
            self._plot = plot_rpe_jitter(series, self.work / "rpe_jitter.png", title)
        return self._evaluation

    @property
    def plot(self) -> Path | None:
        self.evaluation()
        return self._plot


def variant_augment_spec(variant: Variant) -> AugmentSpec:
    """The augmentation spec of a variant (its job spec's, as the service's): one object,
    or several (``objects``), moving ones with their ``motion``."""
    return AugmentSpec.from_job_spec(variant.job_spec())


def combined_gauge(gauges: list[dict[str, Any] | None]) -> dict[str, Any] | None:
    """The gauge summary over several objects: intrusion frames and annotated frames at
    most (any object's), the smallest lateral distance, the track distances' span; the
    one object's summary as is. None when no object has one."""
    have = [g for g in gauges if g]
    if len(gauges) == 1 or not have:
        return have[0] if have else None
    dists = [d for g in have for d in (g.get("track_distance_m") or [])]
    return {
        "intrusion_frames": max(int(g.get("intrusion_frames") or 0) for g in have),
        "annotated_frames": max(int(g.get("annotated_frames") or 0) for g in have),
        "lateral_distance_m": min(float(g["lateral_distance_m"]) for g in have),
        "track_distance_m": [min(dists), max(dists)] if dists else None,
        "objects_intruding": sum(int(g.get("intrusion_frames") or 0) > 0 for g in have),
        "outline": have[0].get("outline"),
    }


def quality_of(
    evaluation: Mapping[str, Any], augmentation: Mapping[str, Any], cameras: list[str]
) -> dict[str, dict[str, float | None]]:
    """Per camera: the paper's RPE / jitter means (the chosen strategy) and the median
    per-frame placement bound (see :class:`VariantRecord`)."""
    strategy = evaluation.get("strategy")
    paper = evaluation.get("paper_rpe") or {}
    bounds = augmentation.get("placement_bound_px") or {}
    out: dict[str, dict[str, float | None]] = {}
    for cam in cameras:
        r = (paper.get(cam) or {}).get(strategy) or {}
        b = bounds.get(cam) or {}
        out[cam] = {
            "rpe_px_mean": _num(r.get("rpe_mean")),
            "jitter_px_mean": _num(r.get("jitter_mean")),
            "bound_px_median": _num(b.get("median")),
        }
    return out


def _num(x: Any) -> float | None:
    return None if x is None else float(x)


def run_variant(
    variant: Variant,
    ctx: SequenceContext,
    out_dir: Path,
    *,
    workers: int = 1,
    campaign: Mapping[str, Any] | None = None,
) -> VariantRecord:
    """Make one variant: augmentation, report, archive, contact frame, record.

    A variant the augmentation refuses (AugmentError, PlacementError, a broken sequence)
    fails alone: its record says why. Anything else propagates.
    """
    ctx.evaluation()  # once per sequence, not counted in the variant's seconds
    tic = time.perf_counter()
    work = out_dir / ".work" / variant.id
    shutil.rmtree(work, ignore_errors=True)
    seq_out = work / "output" / ctx.folder.name
    try:
        spec = variant_augment_spec(variant)
        aug = augment(
            ctx.folder, spec, seq_out, prepared=ctx.prepared, workers=workers, overwrite=True
        )
    except (AugmentError, PlacementError, SequenceError, ValueError) as exc:
        shutil.rmtree(work, ignore_errors=True)
        log.warning("variant %s failed: %s", variant.id, exc)
        return VariantRecord(
            variant=variant.id,
            key=variant.key,
            state="failed",
            error=str(exc),
            seconds=time.perf_counter() - tic,
        )
    evaluation, series = ctx.evaluation()
    s = ctx.prepared.summary
    metrics = {
        "campaign": dict(campaign or {}),
        "variant": variant.model_dump(mode="json"),
        "sequence": {
            "name": ctx.folder.name,
            "label": variant.sequence_label,
            "frames": aug["frames"]["total"],
        },
        "preparation": {
            "key": ctx.prepared.key,
            "reused": bool(s.get("reused")),
            "strategy": ctx.prepared.strategy,
            "seconds": s.get("total_seconds"),
        },
        "augmentation": aug,
        "evaluation": {**evaluation, "per_frame": series},
    }
    report = work / "report"
    report.mkdir(parents=True, exist_ok=True)
    (report / "metrics.json").write_text(json.dumps(jsonable(metrics), indent=1, sort_keys=True))
    extra: dict[str, Path] = {"metrics.json": report / "metrics.json"}
    if ctx.plot is not None:
        extra["report/rpe_jitter.png"] = ctx.plot
    for p in make_previews(
        seq_out, spec.camera_names(ctx.cameras), report / "previews", lidar=spec.lidar
    ):
        extra[f"report/previews/{p.name}"] = p
    # the contact frame is read from the output before the archive is made
    cameras = spec.camera_names(ctx.cameras)
    uuids = [o.get("uuid") for o in aug.get("objects") or [aug.get("object") or {}]]
    frame = contact_frame(seq_out, [u for u in uuids if u], cameras[0])
    thumb = f"thumbs/{variant.id}.png"
    write_thumbnail(frame, out_dir / thumb)
    name = archive_name(variant)
    archive = build_archive(seq_out, out_dir / name, extra=extra)
    shutil.rmtree(work, ignore_errors=True)
    return VariantRecord(
        variant=variant.id,
        key=variant.key,
        state="done",
        archive=name,
        archive_bytes=archive.stat().st_size,
        seconds=time.perf_counter() - tic,
        strategy=ctx.prepared.strategy,
        annotated_frames=int(aug["frames"]["annotated"]),
        visible_frames={c: int(v["visible_frames"]) for c, v in aug["cameras"].items()},
        gauge=combined_gauge([o.get("gauge") for o in aug.get("objects") or []])
        if aug.get("objects")
        else aug.get("gauge"),
        object_gauges=[o.get("gauge") for o in aug.get("objects") or []],
        quality=quality_of(evaluation, aug, cameras),
        contact={
            "frame": frame.frame_idx,
            "camera": frame.camera,
            "bbox": None if frame.bbox is None else list(frame.bbox),
            "thumb": thumb,
        },
    )


# ---------------------------------------------------------------------------- a campaign
def write_dry_run(out_dir: Path, spec: CampaignSpec, variants: list[Variant]) -> Path:
    """``variants.json`` (the expansion) in ``out_dir``; nothing else is written."""
    write_atomic(out_dir / "variants.json", dump_variants(variants).encode())
    return out_dir / "variants.json"


def run_campaign(
    spec: CampaignSpec,
    spec_path: str | Path,
    out_dir: str | Path,
    *,
    cache_dir: str | Path | None,
    workers: int = 1,
    base: str | Path | None = None,
    dry_run: bool = False,
    on_variants: Callable[[list[Variant], list[str]], None] | None = None,
    on_variant: VariantDone | None = None,
    on_prepared: Callable[[str, float, bool], None] | None = None,
) -> CampaignResult:
    """The whole campaign (module docstring).

    Parameters
    ----------
    spec, spec_path : the validated spec and its file (named in errors and campaign.json).
    out_dir : the campaign's output folder (created; a re-run resumes in it).
    cache_dir : the prepared cache (``Settings.prepared_cache_dir``); None prepares
        without caching.
    workers : processes for each variant's frames (the augmentation's pool).
    base : relative sequence paths are from here (default: the current directory).
    dry_run : expand, write ``variants.json`` and stop (no variant runs).
    on_variants(variants, warnings) : after the expansion; on_variant(variant, record,
        skipped) : after each variant; on_prepared(label, seconds, reused) : per sequence.

    Raises
    ------
    CampaignRunError : the spec cannot run as asked (message names the file and field).
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    folders = sequence_folders(spec, spec_path, base)
    check_runnable(spec, spec_path)
    prepared, prepare_s = prepare_sequences(
        spec, folders, cache_dir=cache_dir, spec_path=spec_path, on_prepared=on_prepared
    )
    variants, warnings = expand_campaign(spec, prepared, spec_path)
    if on_variants is not None:
        on_variants(variants, warnings)
    out_dir.mkdir(parents=True, exist_ok=True)
    if dry_run:
        write_dry_run(out_dir, spec, variants)
        return CampaignResult(
            spec,
            out_dir,
            variants,
            {v.id: None for v in variants},
            [],
            time.perf_counter() - t0,
            prepare_s,
        )
    campaign = {"name": spec.name, "seed": spec.seed, "spec_file": str(spec_path)}
    write_json_atomic(out_dir / "campaign.json", {**campaign, "spec": spec.model_dump(mode="json")})
    write_atomic(out_dir / "variants.json", dump_variants(variants).encode())
    contexts = _sequence_contexts(spec, folders, prepared, out_dir)
    records: dict[str, VariantRecord | None] = {}
    skipped: list[str] = []
    try:
        for v in variants:
            rec, done = _run_or_resume(v, contexts[v.sequence], out_dir, workers, campaign)
            if done:
                skipped.append(v.id)
            records[v.id] = rec
            if on_variant is not None:
                on_variant(v, rec, v.id in skipped)
    finally:
        # an interruption still leaves a manifest of what is done (the rest pending)
        for v in variants:
            records.setdefault(v.id, None)
        evaluate_s = {k: c.evaluation_s for k, c in contexts.items() if c.evaluation_s is not None}
        result = CampaignResult(
            spec,
            out_dir,
            variants,
            records,
            skipped,
            time.perf_counter() - t0,
            prepare_s,
            evaluate_s,
        )
        _write_outputs(result)
        shutil.rmtree(out_dir / ".work", ignore_errors=True)
    result.wall_s = time.perf_counter() - t0
    return result


def _sequence_contexts(
    spec: CampaignSpec,
    folders: Mapping[str, Path],
    prepared: Mapping[str, PreparedSequence],
    out_dir: Path,
) -> dict[str, SequenceContext]:
    """Per sequence key its context: folder, prepared sequence, cameras, scratch folder."""
    return {
        e.key: SequenceContext(
            folders[e.key],
            prepared[e.key],
            list(spec.job.cameras),
            out_dir / ".work" / f"sequence_{i}",
        )
        for i, e in enumerate(spec.sequences)
    }


def _run_or_resume(
    v: Variant, ctx: SequenceContext, out_dir: Path, workers: int, campaign: dict[str, Any]
) -> tuple[VariantRecord, bool]:
    """One variant's record: the one on disk when it is complete already (True), else
    the variant run now and its record written (False)."""
    rec = complete_record(out_dir, v)
    if rec is not None:
        log.info("variant %s complete already: skipped", v.id)
        return rec, True
    _forget(out_dir, v)
    rec = run_variant(v, ctx, out_dir, workers=workers, campaign=campaign)
    write_json_atomic(record_path(out_dir, v), rec.to_json())
    log.info("variant %s %s in %.1f s", v.id, rec.state, rec.seconds or 0.0)
    return rec, False


def _write_outputs(result: CampaignResult) -> None:
    rows = manifest_rows(result.spec, result.variants, result.records)
    summary = {
        "variants": len(result.variants),
        "done": sum(r is not None and r.state == "done" for r in result.records.values()),
        "failed": len(result.failed),
        "skipped": len(result.skipped),
        "wall_s": round(result.wall_s, 3),
        "prepare_s": {k: round(v, 3) for k, v in result.prepare_s.items()},
        "evaluate_s": {k: round(v, 3) for k, v in result.evaluate_s.items()},
    }
    result.manifest_json, result.manifest_csv = write_manifest(
        result.out_dir, result.spec, rows, summary, cameras=list(result.spec.job.cameras)
    )
    result.contact_sheet = write_contact_sheet(result.out_dir, result.variants, result.records)


__all__ = [
    "CampaignResult",
    "CampaignRunError",
    "SequenceContext",
    "VariantRecord",
    "archive_name",
    "check_assets",
    "check_runnable",
    "combined_gauge",
    "complete_record",
    "expand_campaign",
    "load_campaign",
    "prepare_sequences",
    "run_campaign",
    "run_variant",
    "sequence_folders",
    "variant_augment_spec",
    "write_dry_run",
]
