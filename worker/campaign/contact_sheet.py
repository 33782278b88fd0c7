"""The campaign's contact sheet: one frame per variant in a labelled grid (PNG).

Each variant's frame is the one where its objects' bounding boxes are largest (their
areas summed) in the first camera of the job (the middle frame when no object shows in
any frame); the boxes are drawn on it. The thumbnail is written when the variant finishes
(``thumbs/<vid>.png``, read from the augmented output before it is archived), and the
sheet is assembled from the thumbnails, so a resumed run does not open the archives
again. Labels: the variant id and
sequence, the class and seed, the gauge flag and the paper RPE of the camera.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image, ImageDraw, ImageFont

from worker.campaign.manifest import write_atomic
from worker.campaign.variant import Variant
from worker.osdar.sequence import Sequence

if TYPE_CHECKING:  # the record's type only; run.py imports this module
    from worker.campaign.run import VariantRecord

CONTACT_SHEET = "contact_sheet.png"
THUMB_WIDTH_PX = 320
LABEL_LINES = 3
LINE_PX = 13
PAD_PX = 6
BOX_RGB = (255, 40, 40)


@dataclass
class ContactFrame:
    """A variant's frame: its index, camera, RGB image and the (first) object's bbox
    [x_center, y_center, width, height] px (None: not visible, the middle frame);
    ``boxes``: every object's bbox in that frame."""

    frame_idx: int
    camera: str
    image: NDArray[np.uint8]
    bbox: tuple[float, float, float, float] | None
    boxes: list[tuple[float, float, float, float]] = field(default_factory=list)


def object_boxes(labels_raw: Mapping[str, Any], object_uuid: str, camera: str) -> dict[int, Any]:
    """frame -> the object's bbox [xc, yc, w, h] in ``camera`` (OpenLABEL, annotations.py)."""
    out: dict[int, Any] = {}
    for key, frame in (labels_raw.get("openlabel", {}).get("frames") or {}).items():
        data = ((frame.get("objects") or {}).get(object_uuid) or {}).get("object_data") or {}
        for box in data.get("bbox", []):
            if box.get("coordinate_system") == camera:
                out[int(key)] = [float(v) for v in box["val"]]
    return out


def contact_frame(
    seq_folder: str | Path, object_uuid: str | list[str] | None, camera: str
) -> ContactFrame:
    """The frame of the augmented sequence where the objects (one UUID or several) are
    largest in ``camera``."""
    seq = Sequence.open(seq_folder)
    uuids = [object_uuid] if isinstance(object_uuid, str) else list(object_uuid or [])
    per = [object_boxes(seq.labels.raw, u, camera) for u in uuids]
    frames = sorted({f for boxes in per for f in boxes})
    if frames:
        f = max(frames, key=lambda k: sum(b[k][2] * b[k][3] for b in per if k in b))
        boxes = [tuple(b[f]) for b in per if f in b]
        bbox: tuple[float, float, float, float] | None = boxes[0]
    else:
        all_frames = seq.frame_indices
        f, bbox, boxes = all_frames[len(all_frames) // 2], None, []
    img = np.asarray(seq.image(f, camera))
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return ContactFrame(f, camera, img.astype(np.uint8), bbox, boxes)


def thumbnail(frame: ContactFrame, width: int = THUMB_WIDTH_PX) -> Image.Image:
    """The frame scaled to ``width`` px with the object's box drawn on it."""
    im = Image.fromarray(frame.image)
    k = width / im.width
    im = im.resize((width, max(1, round(im.height * k))), Image.Resampling.LANCZOS)
    draw = ImageDraw.Draw(im)
    for box in frame.boxes or ([] if frame.bbox is None else [frame.bbox]):
        xc, yc, w, h = (v * k for v in box)
        draw.rectangle(
            [xc - w / 2 - 2, yc - h / 2 - 2, xc + w / 2 + 2, yc + h / 2 + 2],
            outline=BOX_RGB,
            width=2,
        )
    return im


def _png(im: Image.Image) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


def write_thumbnail(frame: ContactFrame, path: str | Path, width: int = THUMB_WIDTH_PX) -> Path:
    return write_atomic(Path(path), _png(thumbnail(frame, width)))


def tile_label(variant: Variant, record: VariantRecord | None) -> list[str]:
    """The tile's lines: id and sequence; class and seed; state, gauge flag and RPE."""
    classes = ", ".join(f"{o.class_name} #{o.variation_seed}" for o in variant.objects)
    if record is None or record.state != "done":
        state = "pending" if record is None else f"FAILED: {record.error or ''}"
        return [f"{variant.id} {variant.sequence_label}", classes, state[:60]]
    g = record.gauge or {}
    flag = ("INTRUDES" if int(g.get("intrusion_frames") or 0) > 0 else "clear") if g else "no gauge"
    if len(variant.objects) > 1 and g:
        flag = f"{int(g.get('objects_intruding') or 0)}/{len(variant.objects)} intrude"
    if any(o.motion is not None for o in variant.objects):
        flag += "  moving"
    q = next(iter(record.quality.values()), {}) if record.quality else {}
    rpe = q.get("rpe_px_mean")
    rpe_txt = "RPE -" if rpe is None else f"RPE {rpe:.1f} px"
    frame = (record.contact or {}).get("frame")
    return [f"{variant.id} {variant.sequence_label}", classes, f"{flag}  {rpe_txt}  frame {frame}"]


def contact_sheet(
    tiles: list[tuple[Image.Image | None, list[str]]], *, width: int = THUMB_WIDTH_PX
) -> Image.Image:
    """A grid of the tiles (image or None for a grey placeholder, label lines below)."""
    n = max(1, len(tiles))
    cols = min(n, max(1, math.ceil(math.sqrt(n * 1.3))))
    rows = math.ceil(n / cols)
    img_h = max((im.height for im, _ in tiles if im is not None), default=round(width * 0.65))
    cell_w, cell_h = width + 2 * PAD_PX, img_h + LABEL_LINES * LINE_PX + 2 * PAD_PX
    sheet = Image.new("RGB", (cols * cell_w, rows * cell_h), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default()
    for i, (im, lines) in enumerate(tiles):
        x, y = (i % cols) * cell_w + PAD_PX, (i // cols) * cell_h + PAD_PX
        if im is None:
            draw.rectangle([x, y, x + width - 1, y + img_h - 1], fill=(70, 70, 70))
        else:
            sheet.paste(im, (x, y))
        for j, line in enumerate(lines[:LABEL_LINES]):
            draw.text((x, y + img_h + 1 + j * LINE_PX), line, fill=(235, 235, 235), font=font)
    return sheet


def write_contact_sheet(
    out_dir: str | Path,
    variants: list[Variant],
    records: Mapping[str, VariantRecord | None],
) -> Path | None:
    """``contact_sheet.png`` in ``out_dir`` from the variants' thumbnails (None: no
    variants)."""
    if not variants:
        return None
    out_dir = Path(out_dir)
    tiles: list[tuple[Image.Image | None, list[str]]] = []
    for v in variants:
        rec = records.get(v.id)
        thumb = None if rec is None or rec.contact is None else out_dir / rec.contact["thumb"]
        im = None
        if thumb is not None and thumb.is_file():
            with Image.open(thumb) as opened:
                im = opened.convert("RGB")
        tiles.append((im, tile_label(v, rec)))
    return write_atomic(out_dir / CONTACT_SHEET, _png(contact_sheet(tiles)))


__all__ = [
    "CONTACT_SHEET",
    "ContactFrame",
    "contact_frame",
    "contact_sheet",
    "object_boxes",
    "thumbnail",
    "write_contact_sheet",
    "write_thumbnail",
]
