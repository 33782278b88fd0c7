"""An OSDaR23 sequence folder: validated on opening, data read lazily.

:meth:`Sequence.open` reads the labels file and checks that every file the labels name
exists and is not empty (without reading any image or cloud). A stream none of whose
files exist is calibration-only (its calibration is still in the labels); a stream with
some files but not all is an error naming the first missing file. A frame number missing
from the counter sequence (dropped by the recorder, absent from the labels too) is
survivable and warned about.
"""

from __future__ import annotations

import hashlib
import logging
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from worker.osdar.errors import SequenceError, warn_sequence
from worker.osdar.images import DEFAULT_MAX_PIXELS, read_png
from worker.osdar.ins_tables import CorrImu, InsPva, InsStdDev, _Table
from worker.osdar.labels import Labels, load_labels
from worker.osdar.novatel import DataFileName, list_data_files, read_ins_folder
from worker.osdar.pcd import PointCloud, finite_mask, read_pcd

logger = logging.getLogger(__name__)

INSPVA_DIR = "novatel_oem7_inspva"
INSSTDEV_DIR = "novatel_oem7_insstdev"
CORRIMU_DIR = "novatel_oem7_corrimu"


def find_labels_file(folder: Path) -> Path:
    """``<folder.name>_labels.json``, else the single ``*_labels.json`` of the folder."""
    preferred = folder / f"{folder.name}_labels.json"
    if preferred.is_file():
        return preferred
    candidates = sorted(p for p in folder.glob("*_labels.json") if p.is_file())
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise SequenceError(folder, f"no labels file ({preferred.name} or *_labels.json)")
    names = [p.name for p in candidates]
    raise SequenceError(folder, f"several labels files, none named {preferred.name}: {names}")


def uri_to_path(folder: Path, uri: str) -> Path:
    """File of a labels uri (``/rgb_center/012_....png``, relative to the sequence folder)."""
    rel = uri.lstrip("/")
    path = folder / rel
    if not rel or ".." in Path(rel).parts:
        raise SequenceError(folder, f"uri {uri!r} does not name a file inside the sequence")
    return path


@dataclass
class Sequence:
    """An opened OSDaR23 sequence (use :meth:`open`).

    Attributes
    ----------
    folder : Path
        The sequence folder.
    labels_path : Path
        Its labels file.
    labels : Labels
        Parsed labels (``labels.raw`` is the JSON document).
    stream_files : dict of str to dict of int to Path
        Stream -> frame index -> file, for the streams that have files.
    """

    folder: Path
    labels_path: Path
    labels: Labels
    stream_files: dict[str, dict[int, Path]] = field(default_factory=dict)

    # -- opening ------------------------------------------------------------------------

    @classmethod
    def open(cls, folder: str | Path) -> Sequence:
        """Open and validate a sequence folder.

        Raises
        ------
        SequenceError
            Missing folder or labels, unparsable labels, a missing or empty data file.
        """
        folder = Path(folder)
        if not folder.is_dir():
            raise SequenceError(folder, "sequence folder missing")
        labels_path = find_labels_file(folder)
        labels = load_labels(labels_path)
        if not labels.frames:
            raise SequenceError(labels_path, "labels file has no frames")
        seq = cls(folder, labels_path, labels)
        seq.stream_files = _check_stream_files(folder, labels)
        _warn_dropped_frames(labels_path, seq.frame_indices)
        return seq

    @property
    def name(self) -> str:
        """Sequence name (the folder name)."""
        return self.folder.name

    @property
    def frame_indices(self) -> list[int]:
        """Sorted frame numbers."""
        return [f.index for f in self.labels.frames]

    @property
    def cameras(self) -> list[str]:
        """Streams of type camera that have files (labels order)."""
        return [
            name
            for name, s in self.labels.streams.items()
            if s.type == "camera" and name in self.stream_files
        ]

    @property
    def lidar_stream(self) -> str | None:
        """The lidar stream with files (``lidar`` preferred), else None."""
        names = [
            n
            for n, s in self.labels.streams.items()
            if s.type == "lidar" and n in self.stream_files
        ]
        if "lidar" in names:
            return "lidar"
        return names[0] if names else None

    # -- files --------------------------------------------------------------------------

    def path(self, frame_idx: int, stream: str) -> Path:
        """The file of ``stream`` in frame ``frame_idx``.

        Raises
        ------
        KeyError
            No such frame.
        SequenceError
            The stream has no files (calibration-only or unknown) or none in this frame.
        """
        if frame_idx not in self.frame_indices:
            raise KeyError(f"{self.labels_path}: no frame {frame_idx}")
        files = self.stream_files.get(stream)
        if files is None:
            raise SequenceError(self.folder / stream, "stream has no data files in this sequence")
        if frame_idx not in files:
            raise SequenceError(self.labels_path, f"frame {frame_idx} has no {stream} file")
        return files[frame_idx]

    def image_path(self, frame_idx: int, stream: str) -> Path:
        """The PNG of camera ``stream`` in frame ``frame_idx``."""
        return self.path(frame_idx, stream)

    def image(
        self, frame_idx: int, stream: str, max_pixels: int = DEFAULT_MAX_PIXELS
    ) -> NDArray[np.uint8]:
        """Read one image: RGB uint8 (H, W, 3) or grey (H, W)."""
        return read_png(self.image_path(frame_idx, stream), max_pixels=max_pixels)

    def pcd(self, frame_idx: int, allow_nonfinite: bool = False) -> PointCloud:
        """Read the lidar cloud of one frame.

        Parameters
        ----------
        frame_idx : int
            Frame number.
        allow_nonfinite : bool
            Drop points with NaN/inf coordinates (with a warning) instead of failing.

        Raises
        ------
        SequenceError
            No lidar stream, unreadable cloud, or non-finite coordinates.
        """
        stream = self.lidar_stream
        if stream is None:
            raise SequenceError(self.folder, "sequence has no lidar files")
        path = self.path(frame_idx, stream)
        cloud = read_pcd(path)
        for name in ("x", "y", "z"):
            if name not in cloud.fields:
                raise SequenceError(path, f"point cloud has no {name!r} field")
        mask = finite_mask(cloud)
        bad = int(mask.size - np.count_nonzero(mask))
        if bad:
            if not allow_nonfinite:
                raise SequenceError(path, f"{bad} points with non-finite coordinates")
            warn_sequence(path, f"{bad} points with non-finite coordinates dropped")
            cloud = cloud.select(mask)
        return cloud

    def timestamps(self, stream: str) -> NDArray[np.float64]:
        """(n_frames,) float64 timestamps of ``stream`` per frame (NaN where absent)."""
        return np.array(
            [
                f.streams[stream].timestamp if stream in f.streams else np.nan
                for f in self.labels.frames
            ],
            dtype=np.float64,
        )

    def timestamp_text(self, stream: str) -> dict[int, str]:
        """Frame counter -> ``stream``'s timestamp exactly as the labels write it."""
        return {
            f.index: f.streams[stream].timestamp_str
            for f in self.labels.frames
            if stream in f.streams and f.streams[stream].timestamp_str
        }

    # -- INS ----------------------------------------------------------------------------

    def ins(self) -> InsPva:
        """``novatel_oem7_inspva`` rows (sorted by timestamp)."""
        return self._ins_table(INSPVA_DIR, InsPva)  # type: ignore[return-value]

    def ins_stdev(self) -> InsStdDev:
        """``novatel_oem7_insstdev`` rows (sorted by timestamp)."""
        return self._ins_table(INSSTDEV_DIR, InsStdDev)  # type: ignore[return-value]

    def corr_imu(self) -> CorrImu:
        """``novatel_oem7_corrimu`` rows (sorted by timestamp)."""
        return self._ins_table(CORRIMU_DIR, CorrImu)  # type: ignore[return-value]

    def _ins_table(self, dirname: str, table_cls: type[_Table]) -> _Table:
        folder = self.folder / dirname
        table = read_ins_folder(folder, table_cls)
        counters = {name.counter for name, _ in list_data_files(folder, "csv")}
        missing = [i for i in self.frame_indices if i not in counters]
        if missing:
            warn_sequence(folder, f"no INS CSV for frame(s) {missing}")
        return table

    # -- caching ------------------------------------------------------------------------

    def content_key(self) -> str:
        """sha256 hex over the labels bytes and (relative path, size, mtime_ns) of all files.

        Cheap (stat only, no data read); changes when any file is added, removed, resized
        or touched.
        """
        h = hashlib.sha256()
        h.update(self.labels_path.read_bytes())
        for rel, st in _walk_files(self.folder):
            h.update(f"\0{rel}\0{st.st_size}\0{st.st_mtime_ns}".encode())
        return h.hexdigest()


def _walk_files(folder: Path) -> list[tuple[str, os.stat_result]]:
    """(posix relative path, stat) of every regular file under ``folder``, sorted."""
    out = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in files:
            p = Path(root) / name
            out.append((p.relative_to(folder).as_posix(), p.stat()))
    out.sort(key=lambda item: item[0])
    return out


def _check_stream_files(folder: Path, labels: Labels) -> dict[str, dict[int, Path]]:
    """Stream -> frame -> file for streams with files; raise on a missing or empty one."""
    per_stream: dict[str, dict[int, Path]] = {}
    for frame in labels.frames:
        for name, fs in frame.streams.items():
            per_stream.setdefault(name, {})[frame.index] = uri_to_path(folder, fs.uri)
    result: dict[str, dict[int, Path]] = {}
    for name, files in per_stream.items():
        sizes = {i: _file_size(p) for i, p in files.items()}
        if all(s is None for s in sizes.values()):
            logger.info("%s: stream %s has no files: calibration only", folder, name)
            continue
        for i, p in files.items():
            if sizes[i] is None:
                raise SequenceError(p, f"data file of stream {name!r}, frame {i} missing")
            if sizes[i] == 0:
                raise SequenceError(p, f"data file of stream {name!r}, frame {i} is empty")
            _check_counter(p, i)
        result[name] = files
    return result


def _file_size(path: Path) -> int | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size if stat.S_ISREG(st.st_mode) else None


def _check_counter(path: Path, frame_idx: int) -> None:
    try:
        counter = DataFileName.parse(path).counter
    except SequenceError:
        return  # names not following the pattern are allowed, the labels are authoritative
    if counter != frame_idx:
        logger.info("%s: file counter %d differs from frame %d", path, counter, frame_idx)


def _warn_dropped_frames(labels_path: Path, indices: list[int]) -> None:
    expected = range(indices[0], indices[-1] + 1)
    dropped = sorted(set(expected) - set(indices))
    if dropped:
        warn_sequence(
            labels_path,
            f"frame(s) {dropped} missing from the counter sequence "
            f"{indices[0]}..{indices[-1]} (dropped frames)",
        )
