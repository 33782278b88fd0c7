"""The three NovAtel OEM7 CSV folders of an OSDaR23 sequence: read and write.

Each folder (``novatel_oem7_inspva``, ``novatel_oem7_insstdev``, ``novatel_oem7_corrimu``)
holds one CSV file per frame named ``<counter>_<timestamp>.csv``: a header row with the
column names of the matching table of :mod:`worker.osdar.ins_tables`, then one (or more)
data rows. Values stay in the file's units (degrees, metres, m/s).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import re
from dataclasses import dataclass, fields
from pathlib import Path, PurePosixPath

import numpy as np

from worker.osdar.errors import SequenceError, atomic_write_bytes, warn_sequence
from worker.osdar.ins_tables import CorrImu, InsPva, InsStdDev, _Table

logger = logging.getLogger(__name__)

INS_FOLDERS: dict[str, type[_Table]] = {
    "novatel_oem7_inspva": InsPva,
    "novatel_oem7_insstdev": InsStdDev,
    "novatel_oem7_corrimu": CorrImu,
}
FILE_NAME = re.compile(r"^(?P<counter>\d+)_(?P<timestamp>\d+(?:\.\d*)?)\.(?P<ext>[A-Za-z0-9]+)$")


@dataclass(frozen=True)
class DataFileName:
    """A parsed ``<counter>_<timestamp>.<ext>`` file name.

    Attributes
    ----------
    counter : int
        Frame number.
    timestamp_str : str
        The timestamp exactly as written in the name.
    timestamp : float
        The same as float64 UNIX seconds.
    """

    counter: int
    timestamp_str: str
    timestamp: float

    @classmethod
    def parse(cls, path: str | Path) -> DataFileName:
        """Parse ``path``'s name; SequenceError if it is not ``<counter>_<timestamp>.<ext>``."""
        m = FILE_NAME.match(Path(path).name)
        if m is None:
            raise SequenceError(path, "file name is not <counter>_<timestamp>.<ext>")
        return cls(int(m["counter"]), m["timestamp"], float(m["timestamp"]))


def list_data_files(folder: str | Path, ext: str) -> list[tuple[DataFileName, Path]]:
    """The ``<counter>_<timestamp>.<ext>`` files of ``folder``, sorted by timestamp.

    Raises
    ------
    SequenceError
        The folder is missing, or a file with that extension has another name pattern.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise SequenceError(folder, "folder missing")
    found = [(DataFileName.parse(p), p) for p in folder.glob(f"*.{ext}") if p.is_file()]
    found.sort(key=lambda item: (item[0].timestamp, item[0].counter))
    return found


def _integer_columns(table_cls: type[_Table]) -> set[str]:
    return {f.name for f in fields(table_cls) if "I64" in str(f.type) or f.type is int}


def read_ins_csv(path: str | Path, table_cls: type[_Table]) -> dict[str, list[float]]:
    """Rows of one NovAtel CSV file as column lists (NaN rows included).

    Raises
    ------
    SequenceError
        Missing columns (named), a row of the wrong length or an unparsable number (with
        its line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SequenceError(path, f"cannot read CSV: {e}") from e
    rows = list(csv.reader(io.StringIO(text)))
    while rows and not any(c.strip() for c in rows[-1]):
        rows.pop()
    if not rows:
        raise SequenceError(path, "empty CSV file: no header row")
    header = [c.strip() for c in rows[0]]
    wanted = table_cls.columns()
    missing = [c for c in wanted if c not in header]
    if missing:
        raise SequenceError(path, f"CSV lacks the columns {missing} (header: {header})")
    index = {c: header.index(c) for c in wanted}
    out: dict[str, list[float]] = {c: [] for c in wanted}
    for lineno, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise SequenceError(
                path, f"line {lineno}: {len(row)} values for {len(header)} header columns"
            )
        for c in wanted:
            out[c].append(_parse_number(path, lineno, c, row[index[c]]))
    return out


def _parse_number(path: Path, lineno: int, column: str, value: str) -> float:
    try:
        return float(value)
    except ValueError as e:
        raise SequenceError(path, f"line {lineno}: column {column}: not a number {value!r}") from e


def read_ins_folder(folder: str | Path, table_cls: type[_Table]) -> _Table:
    """Read every CSV of a NovAtel folder into one table, sorted by timestamp.

    Parameters
    ----------
    folder : str or Path
        e.g. ``<sequence>/novatel_oem7_inspva``.
    table_cls : type
        :class:`InsPva`, :class:`InsStdDev` or :class:`CorrImu`.

    Returns
    -------
    table_cls
        (n,) columns; integer columns as int64, the others float64. Rows with NaN values
        are dropped with a :class:`SequenceWarning`.

    Raises
    ------
    SequenceError
        Missing folder, no CSV in it, bad file names, missing columns, unparsable values.
    """
    folder = Path(folder)
    files = list_data_files(folder, "csv")
    if not files:
        raise SequenceError(folder, "no <counter>_<timestamp>.csv file in the INS folder")
    columns: dict[str, list[float]] = {c: [] for c in table_cls.columns()}
    for _, path in files:
        part = read_ins_csv(path, table_cls)
        if not part[table_cls.columns()[0]]:
            warn_sequence(path, "CSV has a header but no data row; skipped")
        part = _drop_nan_rows(path, part)
        for c, values in part.items():
            columns[c].extend(values)
    return _to_table(table_cls, columns)


def _drop_nan_rows(path: Path, part: dict[str, list[float]]) -> dict[str, list[float]]:
    n = len(next(iter(part.values())))
    bad = [i for i in range(n) if any(math.isnan(col[i]) for col in part.values())]
    if not bad:
        return part
    warn_sequence(path, f"{len(bad)} row(s) with NaN values dropped (lines {[b + 2 for b in bad]})")
    bad_set = set(bad)
    return {c: [v for i, v in enumerate(col) if i not in bad_set] for c, col in part.items()}


def _to_table(table_cls: type[_Table], columns: dict[str, list[float]]) -> _Table:
    ints = _integer_columns(table_cls)
    arrays = {}
    for c, values in columns.items():
        a = np.asarray(values, dtype=np.float64)
        arrays[c] = a.astype(np.int64) if c in ints else a
    order = np.argsort(arrays["timestamp"], kind="stable")
    return table_cls(**{c: a[order] for c, a in arrays.items()})


def format_number(value: float | int, integer: bool = False) -> str:
    """Full-precision text of one CSV value (``repr`` of the float64, ints as ints)."""
    if integer:
        return str(int(value))
    return repr(float(value))


def write_ins_folder(folder: str | Path, table: _Table, uris_or_names: list[str]) -> list[Path]:
    """Write one CSV file per row of ``table`` into ``folder``.

    Parameters
    ----------
    folder : str or Path
        Destination folder (created).
    table : InsPva, InsStdDev or CorrImu
        n rows.
    uris_or_names : list of str
        n file names (``012_1631441453.300000000.csv``) or uris whose last part is used.

    Returns
    -------
    list of Path
        The files written.
    """
    folder = Path(folder)
    if len(uris_or_names) != len(table):
        raise ValueError(f"{len(uris_or_names)} file names for {len(table)} rows")
    cols = type(table).columns()
    ints = _integer_columns(type(table))
    data = {c: np.asarray(getattr(table, c)) for c in cols}
    written = []
    for i, name in enumerate(uris_or_names):
        row = [format_number(data[c][i], integer=c in ints) for c in cols]
        text = ",".join(cols) + "\n" + ",".join(row) + "\n"
        path = folder / PurePosixPath(name).name
        written.append(atomic_write_bytes(path, text.encode("utf-8")))
    return written
