"""NovAtel OEM7 CSV folders: round trips, missing columns, bad numbers, NaN rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.osdar import SequenceError, SequenceWarning, read_ins_folder, write_ins_folder
from worker.osdar.ins_tables import CorrImu, InsPva, InsStdDev
from worker.osdar.novatel import DataFileName

NAMES = [
    "013_1631441453.400000000.csv",
    "/novatel_oem7_inspva/012_1631441453.300000000.csv",  # uris work too
    "014_1631441453.500000000.csv",
]


def make_table(cls, seed: int = 0):
    rng = np.random.default_rng(seed)
    cols = {c: rng.normal(0, 100, 3) for c in cls.columns()}
    cols["frame_idx"] = np.array([13, 12, 14], dtype=np.int64)
    cols["timestamp"] = np.array([1631441453.4, 1631441453.3, 1631441453.5])
    if cls is InsPva:
        cols["latitude"] = np.array([53.5511123456789, 53.5511223456789, 53.5511323456789])
    if cls is CorrImu:
        cols["gps_week_number"] = np.array([2174, 2174, 2174], dtype=np.int64)
    return cls(**cols)


@pytest.mark.parametrize("cls", [InsPva, InsStdDev, CorrImu])
def test_round_trip_exact(tmp_path: Path, cls) -> None:
    table = make_table(cls)
    written = write_ins_folder(tmp_path / "ins", table, NAMES)
    assert [p.name for p in written] == [Path(n).name for n in NAMES]
    head = written[0].read_text().splitlines()[0]
    assert head == ",".join(cls.columns())
    back = read_ins_folder(tmp_path / "ins", cls)
    order = np.argsort(table.timestamp)  # read back sorted by timestamp
    for c in cls.columns():
        a, b = getattr(table, c)[order], getattr(back, c)
        assert b.dtype == (np.int64 if c in ("frame_idx", "gps_week_number") else np.float64)
        np.testing.assert_array_equal(a, b, err_msg=c)
    assert back.frame_idx.tolist() == [12, 13, 14]


def test_missing_column(tmp_path: Path) -> None:
    folder = tmp_path / "novatel_oem7_inspva"
    write_ins_folder(folder, make_table(InsPva), NAMES)
    bad = folder / "013_1631441453.400000000.csv"
    lines = bad.read_text().splitlines()
    cols = lines[0].split(",")
    keep = [i for i, c in enumerate(cols) if c not in ("azimuth", "pitch")]
    bad.write_text("\n".join(",".join(line.split(",")[i] for i in keep) for line in lines) + "\n")
    with pytest.raises(SequenceError) as info:
        read_ins_folder(folder, InsPva)
    assert info.value.path == bad
    assert "pitch" in info.value.reason and "azimuth" in info.value.reason


def test_unparsable_number_names_file_and_line(tmp_path: Path) -> None:
    folder = tmp_path / "ins"
    write_ins_folder(folder, make_table(InsStdDev), NAMES)
    bad = folder / "014_1631441453.500000000.csv"
    lines = bad.read_text().splitlines()
    lines.append(lines[1].replace(lines[1].split(",")[3], "12,5"))  # decimal comma
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(SequenceError, match="line 3") as info:
        read_ins_folder(folder, InsStdDev)
    assert info.value.path == bad
    lines[2] = lines[1].replace(lines[1].split(",")[3], "n/a")
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(SequenceError, match=r"line 3: column longitude_stdev: not a number 'n/a'"):
        read_ins_folder(folder, InsStdDev)


def test_nan_rows_dropped_with_warning(tmp_path: Path) -> None:
    table = make_table(InsPva)
    table.height[0] = np.nan  # row of 013
    write_ins_folder(tmp_path / "ins", table, NAMES)
    with pytest.warns(SequenceWarning, match="013_1631441453.400000000.csv: 1 row"):
        back = read_ins_folder(tmp_path / "ins", InsPva)
    assert back.frame_idx.tolist() == [12, 14]


def test_missing_folder_and_bad_names(tmp_path: Path) -> None:
    with pytest.raises(SequenceError, match="folder missing"):
        read_ins_folder(tmp_path / "novatel_oem7_inspva", InsPva)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match=r"no <counter>_<timestamp>\.csv"):
        read_ins_folder(tmp_path / "empty", InsPva)
    (tmp_path / "empty" / "frame12.csv").write_text("x\n")
    with pytest.raises(SequenceError, match="file name is not"):
        read_ins_folder(tmp_path / "empty", InsPva)


def test_file_name_parsing() -> None:
    name = DataFileName.parse("/lidar/012_1631441453.299504000.pcd")
    assert name.counter == 12 and name.timestamp_str == "1631441453.299504000"
    assert name.timestamp == pytest.approx(1631441453.299504)


def test_wrong_number_of_names(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="2 file names for 3 rows"):
        write_ins_folder(tmp_path, make_table(InsPva), NAMES[:2])
