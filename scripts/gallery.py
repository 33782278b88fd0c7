# ruff: noqa: T201 (a script: prints what it writes)
"""The README gallery: full-resolution crops of every obstacle class, augmented by the
real pipeline into a sequence.

    .venv/bin/python scripts/gallery.py SEQ [--out docs/figures/gallery] [--frame N]

For each entry of :data:`ENTRIES` (the person in its five poses, two cows, two horses,
an elephant, two rocks, a fallen tree, and an uploaded textured asset: a GLB crate with
a wood-grain base-colour texture and a normal map, written by this script), the frame
``--frame`` of ``--camera`` is augmented with :func:`worker.augmentation.augment.augment`
(preparation cached in ``--cache-dir``; lighting, shadows, LAB matching, blur and the
frame's sensor noise all as in a job), and the crop around the changed pixels (plus a
margin, at most ``--max-size`` px a side about its centre, never scaled) is written as
``<out>/<name>.png``; ``<out>/index.md`` lists them
with their spec. The crops are 1:1 pixels of the camera image.
"""

from __future__ import annotations

import argparse
import io
import logging
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import trimesh
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderer.assets.textures import periodic_noise
from worker.augmentation.augment import augment
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel
from worker.osdar.sequence import Sequence
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import prepare

log = logging.getLogger("gallery")

# name: (object fields, placement "s=..,offset=..,yaw=..")
P = "person"
ENTRIES: dict[str, tuple[dict, str]] = {
    "person_standing": ({"builtin": P, "seed": 1}, "s=22,offset=0.6,yaw=70"),
    "person_walking": ({"builtin": P, "seed": 2, "pose": "walking"}, "s=22,offset=-0.4,yaw=100"),
    "person_lying": ({"builtin": P, "seed": 3, "pose": "lying"}, "s=20,offset=0,yaw=0"),
    "person_crouching": ({"builtin": P, "seed": 4, "pose": "crouching"}, "s=20,offset=0.8,yaw=150"),
    "person_sitting": ({"builtin": P, "seed": 5, "pose": "sitting"}, "s=20,offset=-0.8,yaw=60"),
    "cow_0": ({"builtin": "cow", "seed": 0}, "s=28,offset=0,yaw=80"),
    "cow_3": ({"builtin": "cow", "seed": 3}, "s=28,offset=0.5,yaw=120"),
    "horse_1": ({"builtin": "horse", "seed": 1}, "s=28,offset=0,yaw=70"),
    "horse_4": ({"builtin": "horse", "seed": 4}, "s=28,offset=-0.5,yaw=110"),
    "elephant_2": ({"builtin": "elephant", "seed": 2}, "s=35,offset=0,yaw=75"),
    "rock_0": ({"builtin": "rock", "seed": 0}, "s=18,offset=0,yaw=0"),
    "rock_5": ({"builtin": "rock", "seed": 5}, "s=18,offset=0.4,yaw=40"),
    "fallen_tree_1": ({"builtin": "fallen_tree", "seed": 1}, "s=24,offset=0,yaw=90"),
    "uploaded_crate_glb": (
        {"mesh_path": "CRATE", "file_type": "glb", "name": "crate"},
        "s=20,offset=0,yaw=30",
    ),
}


def crate_glb(size_m: float = 0.9) -> bytes:
    """A wooden crate as a GLB (+Y up): per-face UVs over a plank texture (sRGB base
    colour, 512 px) and a matching normal map, metallic 0, roughness 0.8."""
    rng = np.random.default_rng(7)
    n = 512
    grain = periodic_noise(rng, n, 2.0, stretch=10.0)
    v = np.arange(n)[:, None]
    plank = (v // (n // 5)) % 2
    gap = (v % (n // 5)) < 5
    base = (
        np.array([150.0, 104.0, 60.0])
        * (1.0 + 0.12 * grain[..., None])
        * (1.0 - 0.12 * plank[..., None])
    )
    base[np.repeat(gap, n, axis=1)] = [40.0, 28.0, 18.0]
    frame_ = np.zeros((n, n), bool)
    frame_[:24, :] = frame_[-24:, :] = frame_[:, :24] = frame_[:, -24:] = True
    base[frame_] *= 0.75
    height = 0.6 * grain - 3.0 * np.repeat(gap, n, axis=1) - 1.5 * frame_
    gy, gx = np.gradient(cv2.GaussianBlur(height.astype(np.float32), (5, 5), 1.2))
    nrm = np.dstack([-gx * 0.8, gy * 0.8, np.ones_like(gx)])
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    nimg = np.round((nrm * 0.5 + 0.5) * 255).astype(np.uint8)
    h = size_m / 2
    pos, uv, faces = [], [], []
    for axis in range(3):
        for sgn in (1.0, -1.0):
            nn = np.zeros(3)
            nn[axis] = sgn
            a, b = [(1, 2), (2, 0), (0, 1)][axis]
            ua, ub = np.zeros(3), np.zeros(3)
            ua[a], ub[b] = (1.0 if sgn > 0 else -1.0), 1.0
            k = len(pos)
            for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                pos.append(nn * h + s * ua * h + t * ub * h)
                uv.append([(s + 1) / 2, (t + 1) / 2])  # trimesh: v up
            faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    mat = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(np.clip(base, 0, 255).astype(np.uint8)),
        normalTexture=Image.fromarray(nimg), metallicFactor=0.0, roughnessFactor=0.8,
    )  # fmt: skip
    mesh = trimesh.Trimesh(
        np.array(pos),
        np.array(faces),
        process=False,
        visual=trimesh.visual.TextureVisuals(uv=np.array(uv), material=mat),
    )
    buf = io.BytesIO(mesh.export(file_type="glb"))
    return buf.getvalue()


def changed_box(a: np.ndarray, b: np.ndarray, margin: int) -> tuple[int, int, int, int] | None:
    d = np.any(a != b, axis=2)
    if not d.any():
        return None
    vs, us = np.nonzero(d)
    H, W = d.shape
    return (max(int(us.min()) - margin, 0), max(int(vs.min()) - margin, 0),
            min(int(us.max()) + 1 + margin, W), min(int(vs.max()) + 1 + margin, H))  # fmt: skip


def _capped(box: tuple[int, int, int, int], size: int) -> tuple[int, int, int, int]:
    """The box shrunk about its centre to at most ``size`` px a side (no scaling)."""
    u0, v0, u1, v1 = box
    cu, cv = (u0 + u1) // 2, (v0 + v1) // 2
    if u1 - u0 > size:
        u0, u1 = cu - size // 2, cu - size // 2 + size
    if v1 - v0 > size:
        v0, v1 = cv - size // 2, cv - size // 2 + size
    return u0, v0, u1, v1


def asset_entries(assets: list[str]) -> dict[str, tuple[dict, str]]:
    """``--asset FILE[,key=value...]`` entries: each file at yaw 0 and 180, 20 m ahead."""
    out: dict[str, tuple[dict, str]] = {}
    for text in assets:
        path, *pairs = text.split(",")
        p = Path(path)
        if not p.is_file():
            raise SystemExit(f"--asset {path}: no such file")
        obj: dict = {"mesh_path": str(p), "file_type": p.suffix.lstrip(".").lower()}
        for pair in pairs:
            k, _, v = pair.partition("=")
            obj[k] = v if k in ("up", "name") else float(v)
        for yaw in (0, 180):
            out[f"{p.stem.lower()}_yaw{yaw}"] = (obj, f"s=20,offset=0,yaw={yaw}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--out", type=Path, default=Path("docs/figures/gallery"))
    ap.add_argument("--frame", type=int, default=None, help="default: the first frame")
    ap.add_argument("--camera", default="rgb_highres_center")
    ap.add_argument("--margin", type=int, default=40)
    ap.add_argument("--max-size", type=int, default=1024, help="crop at most this (px), 1:1")
    ap.add_argument("--only", nargs="*", default=None, help="entry names")
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/osdar_bench_cache"))
    ap.add_argument(
        "--asset", action="append", default=[], metavar="FILE[,key=value...]",
        help="a mesh file of your own (e.g. a downloaded sample asset), rendered facing "
        "along the track (yaw 0) and facing the train (yaw 180) instead of the built-in "
        "entries; object fields after commas, e.g. Horse.glb,mesh_scale=0.01,"
        "animation_time_s=0.4",
    )  # fmt: skip
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    seq = Sequence.open(args.sequence)
    frame = seq.frame_indices[0] if args.frame is None else args.frame
    prepared = prepare(args.sequence, PrepareConfig(strategy="auto"), cache_dir=args.cache_dir)
    src = np.asarray(Image.open(seq.image_path(frame, args.camera)).convert("RGB"))
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="osdar_gallery_") as tmp:
        crate = Path(tmp) / "crate.glb"
        crate.write_bytes(crate_glb())
        entries = asset_entries(args.asset) if args.asset else ENTRIES
        for name, (obj, place) in entries.items():
            if args.only and name not in args.only:
                continue
            fields = {k: (str(crate) if v == "CRATE" else v) for k, v in obj.items()}
            spec = AugmentSpec(
                object=ObjectSource(**fields),
                placement=PlacementModel.parse(place),
                cameras=(args.camera,),
                frame_range=(frame, frame),
            )
            out = Path(tmp) / name
            try:
                augment(args.sequence, spec, out, prepared=prepared, evaluate=False,
                        overwrite=True)  # fmt: skip
            except ValueError as exc:  # a placement the scene refuses (a pole, off track)
                print(f"{name}: {exc}: skipped")
                continue
            got = next(out.rglob(seq.image_path(frame, args.camera).name))
            img = np.asarray(Image.open(got).convert("RGB"))
            box = changed_box(src, img, args.margin)
            if box is None:
                print(f"{name}: not visible in frame {frame} of {args.camera}: skipped")
                continue
            u0, v0, u1, v1 = box = _capped(box, args.max_size)
            path = args.out / f"{name}.png"
            Image.fromarray(img[v0:v1, u0:u1]).save(path, optimize=True)
            rows.append((name, obj, place, box))
            print(f"{path}: {u1 - u0} x {v1 - v0} px at ({u0}, {v0})")
            shutil.rmtree(out, ignore_errors=True)
    lines = [
        f"# Gallery: {seq.name}, frame {frame}, {args.camera} (1:1 crops)",
        "",
        "| crop | object | placement | box (u0, v0, u1, v1) |",
        "|---|---|---|---|",
    ]
    for name, obj, place, box in rows:
        desc = ", ".join(f"{k}={v}" for k, v in obj.items() if k != "mesh_path")
        lines.append(f"| ![{name}]({name}.png) | {desc} | {place} | {box} |")
    if args.asset:  # a user's own files: crops only, no gallery index
        return 0
    index = args.out / "index.md"
    if args.only and index.is_file():  # keep the other entries' rows
        old = [ln for ln in index.read_text().splitlines()[4:]
               if not any(f"![{r[0]}]" in ln for r in rows)]  # fmt: skip
        lines[4:4] = old
    index.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
