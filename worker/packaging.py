"""Pipeline step 9, packaging: the output sequence as one archive, with its report.

The archive is a ``.tar.gz`` of one top-level folder named after the sequence, in the
OSDaR23 layout (labels JSON, camera PNGs, lidar PCDs, INS CSVs), plus::

    <name>/metrics.json
    <name>/report/rpe_jitter.png          (when there is something to plot)
    <name>/report/previews/*.png          (small camera frames, lidar bird's-eye view)
    <name>/report/preparation.json        (the preparation summary)

``ground_truth/`` of a synthetic input is not part of the output. The archive is written
beside its final name and renamed into place, so a reader never sees half of it.
"""

from __future__ import annotations

import tarfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from worker.gzip_stored import GzipStoredWriter
from worker.osdar.images import write_png
from worker.osdar.sequence import Sequence

#: Folders of the input never copied into the output.
EXCLUDED = frozenset({"ground_truth"})
PREVIEW_WIDTH_PX = 320
BEV_EXTENT_M = (-20.0, 80.0, -30.0, 30.0)  # x min, x max, y min, y max (lidar frame)
BEV_CELL_M = 0.25
#: Files already compressed: stored in the archive's gzip stream, not deflated again.
STORED_SUFFIXES = frozenset({".png", ".jpg", ".jpeg"})
#: The deflate level of the rest (lidar PCDs, labels, CSVs). Measured on a 40-frame
#: synthetic variant (61.8 MB of files: PNGs 23.5, PCDs 38.1) with ``tarfile``'s single
#: level: 0 (stored) 0.13 s of CPU, 61.8 MB; 1: 1.14 s, 46.2 MB; 6: 2.00 s, 45.1 MB;
#: 9: 4.70 s, 45.1 MB; the PNGs' part of level 1 alone 0.51 s for 0.5 % of their bytes.
#: PNGs stored and the rest at level 1: 0.70 s, 46.3 MB. With ISA-L's deflater
#: (worker/gzip_stored.py) at its level 1, a 10-frame full-density synthetic sequence
#: (45 MB of PCDs): 0.19 s of CPU and 32.6 MB against 0.92 s and 33.2 MB with zlib's.
ARCHIVE_DEFLATE_LEVEL = 1


def preview_frames(frames: list[int]) -> list[int]:
    """First, middle and last frame (fewer when the sequence is shorter)."""
    if not frames:
        return []
    picks = [frames[0], frames[len(frames) // 2], frames[-1]]
    return list(dict.fromkeys(picks))


def _thumbnail(img: np.ndarray, width: int = PREVIEW_WIDTH_PX) -> np.ndarray:

    h, w = img.shape[:2]
    if w <= width:
        return img
    return cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)


def bird_eye_view(xyz: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB uint8 point density of an (n, 3) lidar-frame cloud seen from above."""

    x0, x1, y0, y1 = BEV_EXTENT_M
    nx, ny = round((x1 - x0) / BEV_CELL_M), round((y1 - y0) / BEV_CELL_M)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    hist, _, _ = np.histogram2d(xyz[:, 0], xyz[:, 1], bins=(nx, ny), range=((x0, x1), (y0, y1)))
    grey = np.log1p(hist)
    if grey.max() > 0:
        grey = grey / grey.max()
    # forward (x) up, left (y) to the left
    img = (255 * grey[::-1, ::-1]).astype(np.uint8)
    bgr = cv2.applyColorMap(img, cv2.COLORMAP_INFERNO)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def make_previews(
    seq_folder: str | Path, cameras: list[str], out_dir: str | Path, *, lidar: bool = True
) -> list[Path]:
    """Small PNGs of the first/middle/last frame of each camera and a lidar bird's-eye view.

    Returns the files written, in a stable order.
    """

    seq = Sequence.open(seq_folder)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = preview_frames(seq.frame_indices)
    written: list[Path] = []
    for cam in cameras:
        if cam not in seq.stream_files:
            continue
        for f in frames:
            if f not in seq.stream_files[cam]:
                continue
            path = out_dir / f"{cam}_{f:03d}.png"
            write_png(path, _thumbnail(seq.image(f, cam)), compression=6)
            written.append(path)
    if lidar and seq.lidar_stream is not None and frames:
        f = frames[len(frames) // 2]
        cloud = seq.pcd(f, allow_nonfinite=True)
        path = out_dir / f"lidar_bev_{f:03d}.png"
        write_png(path, bird_eye_view(cloud.xyz), compression=6)
        written.append(path)
    return written


def build_archive(
    seq_folder: str | Path,
    archive: str | Path,
    *,
    extra: dict[str, Path] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Tar+gzip ``seq_folder`` (without ``ground_truth/``) and ``extra`` into ``archive``:
    one gzip member, PNGs stored in it, the rest deflated at ``ARCHIVE_DEFLATE_LEVEL``.

    ``extra`` maps a path inside the sequence folder of the archive (``metrics.json``,
    ``report/...``) to a local file; it replaces a file of the folder at the same path.
    ``progress(files_done, files_total)``.
    """
    seq_folder, archive = Path(seq_folder), Path(archive)
    name = seq_folder.name
    extra = extra or {}
    files = [
        p
        for p in sorted(seq_folder.rglob("*"))
        if p.is_file()
        and p.relative_to(seq_folder).parts[0] not in EXCLUDED
        and p.relative_to(seq_folder).as_posix() not in extra  # ours replace the input's
    ]
    total = len(files) + len(extra)
    archive.parent.mkdir(parents=True, exist_ok=True)
    tmp = archive.with_name(archive.name + ".partial")
    try:
        with open(tmp, "wb") as raw, GzipStoredWriter(raw, level=ARCHIVE_DEFLATE_LEVEL) as gz:
            with tarfile.open(fileobj=gz, mode="w") as tar:  # type: ignore[call-overload]
                for k, path in enumerate(files, 1):
                    gz.stored = path.suffix.lower() in STORED_SUFFIXES
                    tar.add(path, arcname=f"{name}/{path.relative_to(seq_folder).as_posix()}")
                    if progress is not None and (k % 20 == 0 or k == len(files)):
                        progress(k, total)
                for arcname, path in sorted(extra.items()):
                    gz.stored = path.suffix.lower() in STORED_SUFFIXES
                    tar.add(path, arcname=f"{name}/{arcname}")
                gz.stored = False  # the tar's end blocks
        tmp.replace(archive)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if progress is not None:
        progress(total, total)
    return archive
