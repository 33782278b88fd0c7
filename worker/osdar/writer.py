"""Write a sequence in the OSDaR23 layout, all or nothing.

Everything goes to ``<out_folder>.partial``; :meth:`SequenceWriter.finish` writes the
labels file last, checks that every file the labels name was written, and renames the
partial folder into place (one atomic rename), so a reader never sees half a sequence.
:meth:`SequenceWriter.abort` (or an exception inside ``with SequenceWriter(...)``)
removes the partial folder.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from worker.osdar.errors import SequenceError, atomic_write_bytes
from worker.osdar.images import write_png
from worker.osdar.ins_tables import _Table
from worker.osdar.labels import dump_labels, parse_labels
from worker.osdar.novatel import write_ins_folder
from worker.osdar.pcd import PointCloud
from worker.osdar.pcd import write_pcd as _write_pcd_file
from worker.osdar.sequence import uri_to_path

logger = logging.getLogger(__name__)


class SequenceWriter:
    """Writer of one sequence folder.

    Parameters
    ----------
    out_folder : str or Path
        The final sequence folder; must not exist yet unless ``overwrite``.
    labels_raw : dict, optional
        The OpenLABEL document to write at :meth:`finish` (unless one is passed there).
    name : str, optional
        Sequence name; the labels file is ``<name>_labels.json``. Default the folder name.
    overwrite : bool
        Replace an existing ``out_folder`` at :meth:`finish`.
    """

    def __init__(
        self,
        out_folder: str | Path,
        labels_raw: dict[str, Any] | None = None,
        name: str | None = None,
        overwrite: bool = False,
    ) -> None:
        self.out_folder = Path(out_folder)
        self.labels_raw = labels_raw
        self.name = name or self.out_folder.name
        self.overwrite = overwrite
        self.partial = self.out_folder.with_name(self.out_folder.name + ".partial")
        self.finished = False
        if self.out_folder.exists() and not overwrite:
            raise FileExistsError(f"{self.out_folder}: output sequence already exists")
        if self.partial.exists():
            logger.warning("%s: removing a stale partial output", self.partial)
            shutil.rmtree(self.partial)
        self.partial.mkdir(parents=True)

    @property
    def root(self) -> Path:
        """The folder being written (``<out_folder>.partial`` until :meth:`finish`)."""
        return self.partial

    # -- context manager ----------------------------------------------------------------

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self.abort()
        elif not self.finished:
            try:
                self.finish()
            except BaseException:
                self.abort()
                raise

    # -- writing ------------------------------------------------------------------------

    def target(self, rel_uri: str) -> Path:
        """Path inside the partial folder of a uri such as ``/rgb_center/012_....png``."""
        self._check_open()
        return uri_to_path(self.partial, rel_uri)

    def copy_unchanged(self, src_path: str | Path, rel_uri: str) -> Path:
        """Put ``src_path`` byte-identical at ``rel_uri``: hard link, else copy."""
        dest = self.target(rel_uri)
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.unlink(missing_ok=True)
        try:
            os.link(src_path, dest)
        except OSError as e:
            if e.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP):
                raise
            shutil.copyfile(src_path, dest)
        return dest

    def write_image(self, rel_uri: str, rgb: NDArray[np.uint8], compression: int = 1) -> Path:
        """Write an RGB (H, W, 3) or grey (H, W) uint8 image as PNG at ``rel_uri``."""
        return write_png(self.target(rel_uri), rgb, compression=compression)

    def write_pcd(self, rel_uri: str, cloud: PointCloud, data: str | None = None) -> Path:
        """Write a point cloud at ``rel_uri`` (DATA type of its header unless ``data``)."""
        return _write_pcd_file(self.target(rel_uri), cloud, data=data)

    def write_ins(self, folder_name: str, table: _Table, names: list[str]) -> list[Path]:
        """Write a NovAtel folder (e.g. ``novatel_oem7_inspva``): one CSV per row."""
        return write_ins_folder(self.target(folder_name), table, names)

    def write_bytes(self, rel_uri: str, data: bytes) -> Path:
        """Write any other file (``calibration.txt``, ground truth ...) at ``rel_uri``."""
        return atomic_write_bytes(self.target(rel_uri), data)

    # -- finishing ----------------------------------------------------------------------

    def finish(self, labels_raw: dict[str, Any] | None = None) -> Path:
        """Write the labels file, check the files it names, move the folder into place.

        Parameters
        ----------
        labels_raw : dict, optional
            Document to write; default the one given to the constructor.

        Returns
        -------
        Path
            The final sequence folder.

        Raises
        ------
        SequenceError
            A stream has some of its files written but not all of them (streams with no
            file at all are calibration-only).
        """
        self._check_open()
        raw = labels_raw if labels_raw is not None else self.labels_raw
        if raw is None:
            raise ValueError(f"{self.out_folder}: no labels document to finish with")
        labels_path = self.partial / f"{self.name}_labels.json"
        self._check_written(parse_labels(raw, labels_path))
        dump_labels(raw, labels_path)
        if self.out_folder.exists():  # overwrite: checked in __init__
            old = self.out_folder.with_name(self.out_folder.name + ".old")
            shutil.rmtree(old, ignore_errors=True)
            os.rename(self.out_folder, old)
            os.rename(self.partial, self.out_folder)
            shutil.rmtree(old)
        else:
            os.rename(self.partial, self.out_folder)
        self.finished = True
        logger.info("%s: sequence written", self.out_folder)
        return self.out_folder

    def abort(self) -> None:
        """Remove the partial folder; nothing of this writer stays on disk."""
        shutil.rmtree(self.partial, ignore_errors=True)
        self.finished = True

    def _check_open(self) -> None:
        if self.finished:
            raise RuntimeError(f"{self.out_folder}: writer already finished or aborted")

    def _check_written(self, labels: Any) -> None:
        per_stream: dict[str, list[Path]] = {}
        for frame in labels.frames:
            for stream, fs in frame.streams.items():
                per_stream.setdefault(stream, []).append(uri_to_path(self.partial, fs.uri))
        for stream, paths in per_stream.items():
            missing = [p for p in paths if not p.is_file()]
            if missing and len(missing) < len(paths):
                raise SequenceError(
                    missing[0],
                    f"named by the labels but not written ({len(missing)} "
                    f"file(s) of stream {stream!r} missing)",
                )
