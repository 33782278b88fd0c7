"""The augmentation step end to end on small synthetic sequences with ground truth.

"True poses" runs use a PreparedSequence made of the sequence's ground truth
(``truth_prepared``: dense true poses, true centrelines), so every pixel error measured
here is the rendering path's own.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from geometry.camera import CameraModel
from geometry.poses import PoseTrack
from geometry.transforms import invert_T, transform_points
from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import augment_frames
from worker.augmentation.placement import PlacementError
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel, RenderSpec
from worker.cli import main
from worker.evaluation.object_error import truth_prepared
from worker.osdar.pcd import read_pcd

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 6, "scale": 0.15, "lidar_density": 0.2, "seed": 3}


def _generate(folder: Path, **kw: object) -> Path:
    from worker.synth.generator import SynthConfig, generate

    generate(folder, SynthConfig(**{**SEQ, **kw}))
    return folder


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _generate(tmp_path_factory.mktemp("aug") / "fire_aug")


@pytest.fixture(scope="module")
def truth(seq: Path):
    return truth_prepared(seq)


def _spec(seq: Path, place: str, obj: str = "person", **kw: object) -> AugmentSpec:
    return AugmentSpec(
        object=ObjectSource(builtin=obj, **kw),
        placement=PlacementModel.parse(place),
        lidar_origins=str(seq / "ground_truth" / "lidar_origins.json"),
    )


def _run(seq: Path, truth, spec: AugmentSpec, scratch: Path):
    plan = plan_augmentation(seq, spec, truth)
    chunk = augment_frames(plan, plan.frames, scratch)
    return plan, chunk


@pytest.fixture(scope="module")
def truth_run(seq: Path, truth, tmp_path_factory: pytest.TempPathFactory):
    base = tmp_path_factory.mktemp("truth_run")
    # the lidar noise off: the object points must lie exactly on the surface (the noise
    # is tested in test_frame.py)
    spec = _spec(seq, "s=22,offset=0,yaw=90").model_copy(
        update={"render": RenderSpec(lidar_noise=False)}
    )
    plan, chunk = _run(seq, truth, spec, base / "scratch")
    metrics = finish_augmentation(plan, [chunk], base / "fire_aug_person")
    return plan, chunk, metrics, base / "fire_aug_person"


def _cam_times(seq: Path, cam: str) -> dict[int, float]:
    from worker.osdar.sequence import Sequence

    s = Sequence.open(seq)
    return dict(zip(s.frame_indices, s.timestamps(cam), strict=True))


def _true_cameras(seq: Path) -> dict[str, CameraModel]:
    meta = json.loads((seq / "ground_truth" / "meta.json").read_text())
    return {
        n: CameraModel.from_json(c).scaled(meta["scale"])
        for n, c in meta["cameras_full_resolution"].items()
    }


# ---------------------------------------------------------------------------- true poses
def test_anchor_and_mask_land_where_the_ground_truth_says(seq: Path, truth_run) -> None:
    plan, chunk, _, _ = truth_run
    dense = PoseTrack.from_csv(seq / "ground_truth" / "poses_dense.csv")
    cams = _true_cameras(seq)
    p_obj = plan.T_world_obj[:3, 3]
    checked = 0
    for name, cam in cams.items():
        times = _cam_times(seq, name)
        for rec in chunk.frames:
            cr = rec.cameras[name]
            assert cr.visible
            T = dense.interpolate(np.array([times[rec.frame_idx]]))[0]
            uv, ok = cam.project_world(p_obj[None], T)
            assert ok[0]
            assert np.linalg.norm(np.asarray(cr.anchor_uv) - uv[0]) < 0.5
            # The rendered mask's box against the projected vertices' box (unoccluded).
            verts = transform_points(plan.T_world_obj, plan.obj_render.vertices)
            uvv, okv = cam.project_world(verts, T)
            assert okv.all()
            lo, hi = uvv.min(0), uvv.max(0)
            box = np.array(cr.bbox)  # pixel edges
            if cr.visible_fraction > 0.98:
                assert np.all(np.abs(box[:2] - (lo - 0.5 + 0.5)) < 1.6), (box, lo, hi)
                assert np.all(np.abs(box[2:] - hi) < 1.6), (box, lo, hi)
            checked += 1
    assert checked == 2 * len(chunk.frames)


def test_poly2d_and_bbox_match_the_rendered_mask(truth_run) -> None:
    plan, chunk, _, _ = truth_run
    for rec in chunk.frames:
        for name, view in rec.annotation.views.items():
            cam = plan.cameras[name]
            mask = rec.cameras[name].mask((cam.height, cam.width))
            if mask.sum() < 150:
                continue
            poly = np.round(np.asarray(view.outline).reshape(-1, 2)).astype(np.int32)
            filled = np.zeros(mask.shape, np.uint8)
            cv2.fillPoly(filled, [poly], 1)
            iou = np.logical_and(filled > 0, mask).sum() / np.logical_or(filled > 0, mask).sum()
            assert iou > 0.9, (rec.frame_idx, name, iou)
            xc, yc, w, h = view.bbox
            vs, us = np.nonzero(mask)
            assert abs((xc - w / 2) - (us.min() - 0.5)) < 1e-6
            assert abs((yc + h / 2) - (vs.max() + 0.5)) < 1e-6


def test_lidar_object_points_lie_on_the_surface(seq: Path, truth_run) -> None:
    plan, chunk, _, out = truth_run
    scene = o3d.t.geometry.RaycastingScene()
    mesh = plan.obj_full
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    total = 0
    for rec in chunk.frames:
        idx = np.asarray(rec.annotation.lidar_indices, dtype=np.int64)
        uri = plan.uris[rec.frame_idx]["lidar"]
        cloud = read_pcd(out / uri.lstrip("/"))
        src = read_pcd(seq / uri.lstrip("/"))
        assert cloud.header.data == src.header.data and list(cloud.fields) == list(src.fields)
        others = np.setdiff1d(np.arange(len(src)), idx)
        for k in src.fields:  # every other point bit-identical, all fields kept
            assert np.array_equal(cloud.fields[k][others], src.fields[k][others])
        if len(idx) == 0:
            continue
        p_base = np.stack([cloud.fields[k][idx] for k in "xyz"], 1).astype(np.float64)
        T_obj_base = invert_T(plan.T_world_obj) @ plan.T_world_base["lidar"][rec.frame_idx]
        p_obj = transform_points(T_obj_base, p_base)
        d = scene.compute_distance(o3d.core.Tensor(p_obj.astype(np.float32))).numpy()
        assert d.max() < 1e-3
        total += len(idx)
    assert total > 20


def test_output_sequence_is_complete_and_loads(seq: Path, truth_run) -> None:
    import raillabel

    from worker.osdar.labels import validate_openlabel

    _, chunk, metrics, out = truth_run
    files_in = {p.relative_to(seq) for p in seq.rglob("*") if p.is_file()}
    files_out = {p.relative_to(out) for p in out.rglob("*") if p.is_file()}
    labels_in = next(p for p in files_in if p.name.endswith("_labels.json"))
    assert files_in - {labels_in} <= files_out
    for rel in files_in - {labels_in}:
        if rel.suffix not in (".png", ".pcd"):
            assert (seq / rel).read_bytes() == (out / rel).read_bytes(), rel
    labels_path = out / "fire_aug_person_labels.json"
    raw = json.loads(labels_path.read_text())
    assert validate_openlabel(raw) == []
    scene = raillabel.load(labels_path)
    assert len(scene.frames) == len(chunk.frames)
    objs = [o for o in raw["openlabel"]["objects"].values() if "_synthetic_" in o["name"]]
    assert len(objs) == 1 and objs[0]["type"] == "person"
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"]["annotated"] == len(chunk.frames)
    # True poses against the ground truth: the evaluation finds (almost) no error.
    for e in m["object_errors"]["cameras"].values():
        assert e["anchor_px_max"] < 0.5 and e["mask_iou_min"] > 0.95
    assert "frames_render" in m["timings_s"] and metrics["lidar"]["object_points_total"] > 0


def test_augmented_pngs_are_spliced_and_exact(
    seq: Path, truth, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only the rows down to the object's window are decoded and only the rows the object
    changed are compressed anew (worker/osdar/png_splice.py): every changed camera image of
    a job is spliced into its source's PNG, and the file written decodes to exactly the
    composited rows above and the source's below."""
    from worker.augmentation import frame as frame_module

    real = frame_module.splice_decoded
    calls: list[tuple[tuple[int, int], int, int]] = []

    def checked(decoded, img: np.ndarray, rows: tuple[int, int], level: int):
        out = real(decoded, img, rows, level)
        assert out is not None, rows
        got = cv2.imdecode(np.frombuffer(out.png, np.uint8), cv2.IMREAD_UNCHANGED)
        src = cv2.imdecode(np.frombuffer(decoded.src, np.uint8), cv2.IMREAD_UNCHANGED)
        n = img.shape[0]
        np.testing.assert_array_equal(got[:n], img)
        np.testing.assert_array_equal(got[n:], src[n:])
        calls.append((rows, n, decoded.height))
        return out

    real_whole = frame_module.splice_png

    def checked_whole(src: bytes, img: np.ndarray, rows: tuple[int, int], level: int):
        # the frames the plan decoded whole for the lighting
        out = real_whole(src, img, rows, level)
        assert out is not None, rows
        got = cv2.imdecode(np.frombuffer(out, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(got, img)
        calls.append((rows, img.shape[0], img.shape[0]))
        return out

    monkeypatch.setattr(frame_module, "splice_decoded", checked)
    monkeypatch.setattr(frame_module, "splice_png", checked_whole)
    spec = _spec(seq, "s=22,offset=0,yaw=90").model_copy(
        update={"render": RenderSpec(lidar_noise=False)}
    )
    _, chunk = _run(seq, truth, spec, tmp_path / "scratch")
    changed = sum(cr.visible for rec in chunk.frames for cr in rec.cameras.values())
    assert changed > 0 and len(calls) == changed
    # the band is where the object is, not the whole image; above the bottom rows, fewer
    # rows than the image's were decoded
    assert all(0 < r0 < r1 <= n <= h for (r0, r1), n, h in calls)
    assert all(n in (min(r1 + 1, h), h) for (_, r1), n, h in calls)  # down to the band
    assert any(n < h for _, n, h in calls)


def test_the_labels_say_which_builtin_was_placed(truth_run) -> None:
    """Every element of the placed person carries its seed, pose and variant."""
    plan, _, _, out = truth_run
    raw = json.loads((out / "fire_aug_person_labels.json").read_text())["openlabel"]
    oid = next(k for k, o in raw["objects"].items() if "_synthetic_" in o["name"])
    meta = plan.obj_full.meta
    want = {"osdarArSeed": str(meta["seed"]), "osdarArPose": meta["pose"],
            "osdarArVariant": meta["variant"]}  # fmt: skip
    n = 0
    for fd in raw["frames"].values():
        for kind, elems in fd.get("objects", {}).get(oid, {}).get("object_data", {}).items():
            for e in elems:
                text = {t["name"]: t["val"] for t in e["attributes"]["text"]}
                assert {k: text.get(k) for k in want} == want, kind
                n += 1
    assert n > 0


# ---------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def cli_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("prep_cache")


def test_cli_augment_end_to_end(seq: Path, cli_cache: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "fire_cli"
    rc = main(
        ["augment", str(seq), "--object", "rock", "--place", "s=20,offset=0.3,yaw=30",
         "--out", str(out), "--workers", "2", "--cache-dir", str(cli_cache)]
    )  # fmt: skip
    assert rc == 0
    text = capsys.readouterr().out
    assert "wrote" in text and "anchor error" in text
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"]["annotated"] > 0
    for rel in ("novatel_oem7_inspva", "ground_truth"):
        for p in (seq / rel).iterdir():
            assert (out / rel / p.name).read_bytes() == p.read_bytes()


def test_labels_carry_a_placement_bound_per_frame_and_camera(
    seq: Path, cli_cache: Path, tmp_path: Path
) -> None:
    """A real preparation gives pose information: every bbox of the object carries the
    90 % placement bound (px) as a num attribute that raillabel reads, and the metrics
    summarise it per camera."""
    import raillabel

    from worker.augmentation.annotations import PLACEMENT_BOUND_ATTRIBUTE

    out = tmp_path / "fire_bound"
    rc = main(
        ["augment", str(seq), "--object", "person", "--place", "s=22,offset=0,yaw=90",
         "--out", str(out), "--cache-dir", str(cli_cache)]
    )  # fmt: skip
    assert rc == 0
    labels_path = next(out.glob("*_labels.json"))
    raw = json.loads(labels_path.read_text())
    oid = next(k for k, o in raw["openlabel"]["objects"].items() if "_synthetic_" in o["name"])
    bounds = []
    for frame in raw["openlabel"]["frames"].values():
        data = (frame.get("objects") or {}).get(oid, {}).get("object_data", {})
        for bbox in data.get("bbox", []):
            nums = {a["name"]: a["val"] for a in bbox["attributes"]["num"]}
            bounds.append(nums[PLACEMENT_BOUND_ATTRIBUTE])
    assert bounds and all(np.isfinite(b) and 0.0 < b < 1000.0 for b in bounds)
    pointers = raw["openlabel"]["objects"][oid]["object_data_pointers"]
    assert any(
        p["attribute_pointers"].get(PLACEMENT_BOUND_ATTRIBUTE) == "num" for p in pointers.values()
    )
    scene = raillabel.load(labels_path)
    loaded = [
        a.attributes[PLACEMENT_BOUND_ATTRIBUTE]
        for fr in scene.frames.values()
        for a in fr.annotations.values()
        if PLACEMENT_BOUND_ATTRIBUTE in a.attributes
    ]
    assert sorted(loaded) == pytest.approx(sorted(bounds))
    m = json.loads((out / "metrics.json").read_text())
    summary = [s for s in m["placement_bound_px"].values() if s]
    assert summary and all(s["median"] > 0 and s["frames"] > 0 for s in summary)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--place", "s=5000,offset=0,yaw=0"], "off the prepared track"),
        (["--place", "s=20,bogus=1"], "unknown key"),
        (["--object", "unicorn"], "unknown obstacle"),
        (["--cameras", "rgb_left"], "rgb_left"),
    ],
)
def test_cli_user_errors_exit_2(
    seq: Path, cli_cache: Path, tmp_path: Path, capsys, args: list[str], needle: str
) -> None:
    base = ["augment", str(seq), "--object", "person", "--out", str(tmp_path / "o"),
            "--workers", "1", "--cache-dir", str(cli_cache)]  # fmt: skip
    rc = main(base + args)
    assert rc == 2
    err = capsys.readouterr().err
    assert needle in err
    assert not (tmp_path / "o").exists()


def test_cli_inside_a_pole_exit_2(seq: Path, cli_cache: Path, tmp_path: Path, capsys) -> None:
    from worker.preparation.config import PrepareConfig
    from worker.preparation.prepare import prepare

    prepared = prepare(seq, PrepareConfig(), cache_dir=cli_cache)
    if not prepared.poles or prepared.ego is None:
        pytest.skip("preparation found no pole in this small sequence")
    first = min(prepared.track.timestamps)
    p0 = prepared.track.interpolate(np.array([first]))[0, :3, 3]
    s0 = prepared.ego.project(p0[None]).s[0]
    axes = np.array([[*p.axis_xy[:2], p0[2]] for p in prepared.poles])
    pr = prepared.ego.project(axes)
    inside = np.flatnonzero((pr.s > 1.0) & (pr.s < prepared.ego.length - 1.0))
    if len(inside) == 0:
        pytest.skip("no pole beside the prepared ego track")
    k = inside[0]
    place = f"s={pr.s[k] - s0:.3f},offset={pr.lateral[k]:.3f},yaw=0"
    rc = main(["augment", str(seq), "--object", "person", "--place", place,
               "--out", str(tmp_path / "o"), "--cache-dir", str(cli_cache)])  # fmt: skip
    assert rc == 2
    assert "cuts pole" in capsys.readouterr().err


# ---------------------------------------------------------------------------- hard cases
def _check_finite(plan, chunk) -> None:
    for rec in chunk.frames:
        if rec.annotation is None:
            continue
        assert np.all(np.isfinite(rec.annotation.cuboid))
        for name, v in rec.annotation.views.items():
            cam = plan.cameras[name]
            assert np.all(np.isfinite(v.bbox)) and v.bbox[2] > 0 and v.bbox[3] > 0
            xc, yc, w, h = v.bbox
            assert -0.5 - 1e-6 <= xc - w / 2 and xc + w / 2 <= cam.width - 0.5 + 1e-6
            assert -0.5 - 1e-6 <= yc - h / 2 and yc + h / 2 <= cam.height - 0.5 + 1e-6


def test_object_passing_the_camera(seq: Path, truth, tmp_path: Path) -> None:
    """s small: the object is partly outside the image, crosses the near plane, ends up
    behind the cameras; frames where it is not visible are copied byte-identically."""
    plan, chunk = _run(seq, truth, _spec(seq, "s=2.5,offset=0.6,yaw=0", "cow"), tmp_path)
    _check_finite(plan, chunk)
    hidden = 0
    for rec in chunk.frames:
        for name, cr in rec.cameras.items():
            uri = plan.uris[rec.frame_idx][name].lstrip("/")
            if not cr.augmented:
                hidden += 1
                assert (tmp_path / uri).read_bytes() == (seq / uri).read_bytes()
                assert (tmp_path / uri).stat().st_ino == (seq / uri).stat().st_ino
            elif rec.annotation is not None and name in rec.annotation.views:
                assert rec.annotation.views[name].truncated
    assert hidden > 0


def test_tiny_far_object(seq: Path, truth, tmp_path: Path) -> None:
    T0 = truth.track.T[0]
    heading = math.degrees(math.atan2(T0[1, 0], T0[0, 0]))
    p = T0[:3, 3] + 300.0 * T0[:3, 0]
    spec = AugmentSpec(
        object=ObjectSource(builtin="person"),
        placement=PlacementModel(mode="world", xyz=(p[0], p[1], p[2] - 3.5), yaw_deg=heading),
    )
    plan, chunk = _run(seq, truth, spec, tmp_path)
    _check_finite(plan, chunk)
    assert plan.info["render_faces"] <= 400  # a few pixels high: the coarsest LOD
    sizes = [v.bbox[3] for r in chunk.frames if r.annotation for v in r.annotation.views.values()]
    assert sizes and max(sizes) < 12


def test_huge_near_elephant(seq: Path, truth, tmp_path: Path) -> None:
    plan, chunk = _run(seq, truth, _spec(seq, "s=3,offset=0,yaw=90", "elephant"), tmp_path)
    _check_finite(plan, chunk)
    first = chunk.frames[0]
    cam = plan.cameras["rgb_center"]
    view = first.annotation.views["rgb_center"]
    assert view.truncated and view.bbox[2] > 0.8 * cam.width
    assert first.lidar_points > 0


def test_far_origin_sequence(tmp_path: Path) -> None:
    seq = _generate(tmp_path / "far_aug", frames=3, scale=0.1, far_origin=True)
    truth = truth_prepared(seq)
    plan, chunk = _run(seq, truth, _spec(seq, "s=20,offset=0,yaw=90"), tmp_path / "scratch")
    assert (
        np.abs(plan.T_world_obj[:2, 3]).max() > 1e5 or np.abs(truth.track.T[0, :2, 3]).max() < 1e5
    )
    dense = PoseTrack.from_csv(seq / "ground_truth" / "poses_dense.csv")
    for name, cam in _true_cameras(seq).items():
        times = _cam_times(seq, name)
        for rec in chunk.frames:
            cr = rec.cameras[name]
            assert cr.visible
            T = dense.interpolate(np.array([times[rec.frame_idx]]))[0]
            uv, _ = cam.project_world(plan.T_world_obj[:3, 3][None], T)
            assert np.linalg.norm(np.asarray(cr.anchor_uv) - uv[0]) < 0.5


# ---------------------------------------------------------------------------- spec
def test_from_job_spec() -> None:
    spec = AugmentSpec.from_job_spec(
        {
            "sequence_id": "abc",
            "cameras": ["rgb_center"],
            "lidar": False,
            "object": {"builtin": "cow", "scale": 1.2},
            "placement": {"mode": "lidar_frame", "xyz": [20.0, 1.0, 0.0], "frame_idx": 3},
            "frame_range": [2, 5],
            "render": {"png_compression": 4, "shadow": False, "exposure_ms": 0.0},
        }
    )
    assert spec.render.exposure_ms == 0.0 and spec.render.aperture_mm == 4.0
    assert spec.object.builtin == "cow" and spec.object.scale == 1.2
    assert spec.placement.mode == "lidar" and spec.placement.frame_idx == 3
    assert spec.frame_range == (2, 5) and not spec.lidar and spec.cameras == ("rgb_center",)
    assert spec.render.png_compression == 4 and spec.render.shadow_strength == 0.0
    track = AugmentSpec.from_job_spec(
        {"object": {"builtin": "rock"}, "placement": {"mode": "track", "s": 30.0}}
    )
    assert track.placement.yaw_deg == 0.0
    with pytest.raises(ValueError, match="asset"):
        AugmentSpec.from_job_spec(
            {"object": {"asset_id": "x"}, "placement": {"mode": "track", "s": 1}}
        )
    with pytest.raises(PlacementError):
        PlacementModel.parse("s=1,nope=2")


# ---------------------------------------------------------------------------- records
def _same(a: object, b: object) -> bool:
    """Deep equality over dataclasses, pydantic models, arrays, bytes and containers."""
    import dataclasses

    from pydantic import BaseModel

    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, BaseModel):
        return a.model_dump() == b.model_dump()
    if dataclasses.is_dataclass(a):
        return all(_same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and np.isnan(a):
        return bool(np.isnan(b))
    return a == b


def test_plan_and_chunk_records_round_trip_without_pickle(truth_run) -> None:
    """A real plan and chunk through their stored form come back field for field (int
    frame keys, tuples, bytes of the masks, the spec re-validated)."""
    from worker.augmentation.records import dump_chunk, dump_plan, load_chunk, load_plan

    plan, chunk, _, _ = truth_run
    back = load_plan(dump_plan(plan))
    assert _same(back, plan)
    assert all(isinstance(f, int) for f in back.T_world_base[next(iter(back.T_world_base))])
    chunk_back = load_chunk(dump_chunk(chunk))
    assert _same(chunk_back, chunk)
    assert any(c.mask_bits for fr in chunk_back.frames for c in fr.cameras.values())


def test_records_refuse_other_versions_formats_types_and_pickle(truth_run, tmp_path) -> None:
    """A record of another version or format, an unknown type, a missing field and a
    pickle are refused with RecordFormatError; the pickle's code never runs."""
    import io
    import json
    import pickle

    from worker.augmentation import records as rec

    _, chunk, _, _ = truth_run

    def tampered(data: bytes, edit) -> bytes:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            members = {k: z[k] for k in z.files}
        header = json.loads(members["__header__"].tobytes())
        edit(header)
        members["__header__"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
        buf = io.BytesIO()
        np.savez(buf, **members)
        return buf.getvalue()

    data = rec.dump_chunk(chunk)
    with pytest.raises(rec.RecordFormatError, match="version 99; this worker reads"):
        rec.load_chunk(tampered(data, lambda h: h.update(version=99)), "chunks/0000.npz")
    with pytest.raises(rec.RecordFormatError, match=r"expected 'osdar-ar\.plan'"):
        rec.load_plan(data)
    with pytest.raises(rec.RecordFormatError, match="not a record type"):
        rec.load_chunk(tampered(data, lambda h: h["tree"].update(dataclass="Popen")))
    with pytest.raises(rec.RecordFormatError, match="fields missing"):
        rec.load_chunk(tampered(data, lambda h: h["tree"]["fields"].pop("files")))

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (marker.write_text, ("code ran",))

    with pytest.raises(rec.RecordFormatError):
        rec.load_plan(pickle.dumps(Evil()))
    assert not marker.exists()
