"""OSDaR23 sequence I/O: labels (OpenLABEL), PCD clouds, PNG images, NovAtel CSVs.

Read a sequence with :meth:`Sequence.open`, write one in the same layout with
:class:`SequenceWriter`. Layout and conventions: ../shared/design/OSDAR23.md.
"""

from worker.osdar.errors import SequenceError, SequenceWarning
from worker.osdar.images import read_png, write_png
from worker.osdar.labels import (
    CoordinateSystem,
    Frame,
    FrameStream,
    Labels,
    ObjectInfo,
    Stream,
    dump_labels,
    load_labels,
    parse_labels,
    validate_openlabel,
)
from worker.osdar.novatel import INS_FOLDERS, read_ins_folder, write_ins_folder
from worker.osdar.pcd import PcdHeader, PointCloud, finite_mask, read_pcd, write_pcd
from worker.osdar.sequence import Sequence
from worker.osdar.writer import SequenceWriter

__all__ = [
    "INS_FOLDERS",
    "CoordinateSystem",
    "Frame",
    "FrameStream",
    "Labels",
    "ObjectInfo",
    "PcdHeader",
    "PointCloud",
    "Sequence",
    "SequenceError",
    "SequenceWarning",
    "SequenceWriter",
    "Stream",
    "dump_labels",
    "finite_mask",
    "load_labels",
    "parse_labels",
    "read_ins_folder",
    "read_pcd",
    "read_png",
    "validate_openlabel",
    "write_ins_folder",
    "write_pcd",
    "write_png",
]
