"""Sequence folders: opening, validation errors, lazy accessors, PNGs and the writer."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from worker.osdar import (
    Sequence,
    SequenceError,
    SequenceWarning,
    SequenceWriter,
    load_labels,
    read_pcd,
    read_png,
    write_pcd,
    write_png,
)
from worker.osdar.ins_tables import InsPva

RGB = "rgb_center"


def labels_raw(folder: Path) -> dict:
    return json.loads(next(folder.glob("*_labels.json")).read_text())


def uri_path(folder: Path, frame: int, stream: str) -> Path:
    props = labels_raw(folder)["openlabel"]["frames"][str(frame)]["frame_properties"]
    return folder / props["streams"][stream]["uri"].lstrip("/")


def test_open_tiny_sequence(tiny_sequence) -> None:
    folder = tiny_sequence()
    seq = Sequence.open(folder)
    assert seq.name == "tiny_1.1" and seq.frame_indices == [12, 13, 14]
    assert seq.cameras == ["ir_center", "rgb_center"]  # the others are calibration-only
    assert seq.lidar_stream == "lidar"
    assert "rgb_highres_center" in seq.labels.streams  # calibration kept
    img = seq.image(13, RGB)
    assert img.shape == (12, 16, 3) and img.dtype == np.uint8
    assert seq.image(13, "ir_center").shape == (6, 8)
    assert seq.image_path(12, RGB).name == "012_1631441453.300000000.png"
    cloud = seq.pcd(14)
    assert len(cloud) == 40 and cloud.fields["timestamp"].dtype == np.float64
    ts = seq.timestamps("lidar")
    assert ts.shape == (3,) and ts.dtype == np.float64
    assert ts[0] == pytest.approx(1631441453.299504, abs=1e-6)
    ins = seq.ins()
    assert isinstance(ins, InsPva) and ins.frame_idx.tolist() == [12, 13, 14]
    assert len(seq.ins_stdev()) == 3 and seq.corr_imu().gps_week_number.tolist() == [2174] * 3
    with pytest.raises(SequenceError, match="no data files"):
        seq.image(12, "rgb_left")
    with pytest.raises(KeyError):
        seq.image(11, RGB)


def test_content_key(tiny_sequence) -> None:
    folder = tiny_sequence()
    key = Sequence.open(folder).content_key()
    assert len(key) == 64 and key == Sequence.open(folder).content_key()
    png = uri_path(folder, 13, RGB)
    st = png.stat()
    os.utime(png, ns=(st.st_atime_ns, st.st_mtime_ns + 1000))
    assert Sequence.open(folder).content_key() != key


def test_rgb_channel_order(tmp_path: Path) -> None:
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 255  # red
    path = write_png(tmp_path / "red.png", img, compression=9)
    np.testing.assert_array_equal(read_png(path), img)
    import cv2

    assert cv2.imread(str(path))[0, 0].tolist() == [0, 0, 255]  # BGR on disk view


def test_png_guards(tmp_path: Path) -> None:
    path = write_png(tmp_path / "a.png", np.zeros((100, 50, 3), np.uint8))
    with pytest.raises(SequenceError, match="exceeds the limit"):
        read_png(path, max_pixels=4999)
    assert read_png(path, max_pixels=5000).shape == (100, 50, 3)
    fake = tmp_path / "b.png"
    fake.write_bytes(b"GIF89a" + bytes(30))
    with pytest.raises(SequenceError, match="not a PNG") as info:
        read_png(fake)
    assert info.value.path == fake
    trunc = tmp_path / "c.png"
    trunc.write_bytes(path.read_bytes()[:60])
    with pytest.raises(SequenceError, match="could not be decoded"):
        read_png(trunc)


# -- broken sequences ---------------------------------------------------------------------


def test_no_labels(tiny_sequence) -> None:
    folder = tiny_sequence()
    next(folder.glob("*_labels.json")).unlink()
    with pytest.raises(SequenceError, match="no labels file") as info:
        Sequence.open(folder)
    assert info.value.path == folder
    with pytest.raises(SequenceError, match="sequence folder missing"):
        Sequence.open(folder.parent / "nowhere")


def test_missing_frame_file(tiny_sequence) -> None:
    folder = tiny_sequence()
    missing = uri_path(folder, 13, RGB)
    missing.unlink()
    with pytest.raises(SequenceError, match="frame 13 missing") as info:
        Sequence.open(folder)
    assert info.value.path == missing


def test_empty_frame_file(tiny_sequence) -> None:
    folder = tiny_sequence()
    uri_path(folder, 12, "lidar").write_bytes(b"")
    with pytest.raises(SequenceError, match="is empty"):
        Sequence.open(folder)


def test_pcd_header_size_mismatch(tiny_sequence) -> None:
    folder = tiny_sequence()
    pcd = uri_path(folder, 13, "lidar")
    pcd.write_bytes(
        pcd.read_bytes().replace(b"POINTS 40", b"POINTS 41").replace(b"WIDTH 40", b"WIDTH 41")
    )
    seq = Sequence.open(folder)  # lazy: clouds are not read when opening
    with pytest.raises(SequenceError, match="41 x 25 bytes") as info:
        seq.pcd(13)
    assert info.value.path == pcd


def test_csv_without_columns(tiny_sequence) -> None:
    folder = tiny_sequence()
    csv = next((folder / "novatel_oem7_inspva").glob("013_*.csv"))
    csv.write_text("a,b\n1,2\n")
    with pytest.raises(SequenceError, match="lacks the columns") as info:
        Sequence.open(folder).ins()
    assert info.value.path == csv


@pytest.mark.parametrize("data", ["ascii", "binary_compressed"])
def test_nan_coordinates(tiny_sequence, data: str) -> None:
    folder = tiny_sequence(pcd_data=data)
    path = uri_path(folder, 12, "lidar")
    cloud = read_pcd(path)
    cloud.fields["x"][[1, 5]] = np.nan
    cloud.fields["z"][7] = -np.inf
    write_pcd(path, cloud)
    seq = Sequence.open(folder)
    with pytest.raises(SequenceError, match="3 points with non-finite coordinates") as info:
        seq.pcd(12)
    assert info.value.path == path
    with pytest.warns(SequenceWarning, match="3 points with non-finite coordinates dropped"):
        kept = seq.pcd(12, allow_nonfinite=True)
    assert len(kept) == 37 and np.isfinite(kept.xyz).all()


def test_dropped_frame_works_with_warning(tiny_sequence) -> None:
    folder = tiny_sequence(frames=(12, 13, 15, 16))
    with pytest.warns(SequenceWarning, match=r"frame\(s\) \[14\] missing"):
        seq = Sequence.open(folder)
    assert seq.frame_indices == [12, 13, 15, 16]
    assert seq.image(15, RGB).shape == (12, 16, 3) and len(seq.pcd(16)) == 40
    assert len(seq.ins()) == 4


def test_missing_ins_row_and_folder(tiny_sequence) -> None:
    folder = tiny_sequence()
    next((folder / "novatel_oem7_inspva").glob("013_*.csv")).unlink()
    seq = Sequence.open(folder)
    with pytest.warns(SequenceWarning, match=r"no INS CSV for frame\(s\) \[13\]"):
        ins = seq.ins()
    assert ins.frame_idx.tolist() == [12, 14]
    for p in (folder / "novatel_oem7_corrimu").iterdir():
        p.unlink()
    (folder / "novatel_oem7_corrimu").rmdir()
    with pytest.raises(SequenceError, match="folder missing") as info:
        seq.corr_imu()
    assert info.value.path == folder / "novatel_oem7_corrimu"


# -- writer -------------------------------------------------------------------------------


def test_writer_round_trip(tiny_sequence, tmp_path: Path) -> None:
    src = Sequence.open(tiny_sequence())
    out = tmp_path / "out" / "tiny_1.1"
    raw = src.labels.raw
    with SequenceWriter(out, raw, "tiny_1.1") as w:
        assert w.partial.is_dir() and not out.exists()
        for f in src.labels.frames:
            for stream in ("ir_center", "lidar"):
                w.copy_unchanged(src.path(f.index, stream), f.streams[stream].uri)
            w.write_image(f.streams[RGB].uri, 255 - src.image(f.index, RGB))
        ins_tables = {
            "novatel_oem7_inspva": src.ins(),
            "novatel_oem7_insstdev": src.ins_stdev(),
            "novatel_oem7_corrimu": src.corr_imu(),
        }
        for folder, table in ins_tables.items():
            w.write_ins(folder, table, sorted(p.name for p in (src.folder / folder).iterdir()))
        w.write_pcd(src.labels.frames[0].streams["lidar"].uri, src.pcd(12), data="ascii")
        w.finish()
    assert out.is_dir() and not w.partial.exists()
    seq = Sequence.open(out)
    assert seq.labels.raw == raw and seq.frame_indices == [12, 13, 14]
    np.testing.assert_array_equal(seq.image(13, RGB), 255 - src.image(13, RGB))
    assert seq.path(14, "ir_center").read_bytes() == src.path(14, "ir_center").read_bytes()
    assert seq.pcd(12).header.data == "ascii"
    for k, v in src.pcd(12).fields.items():
        np.testing.assert_array_equal(seq.pcd(12).fields[k], v)
    np.testing.assert_array_equal(seq.ins().latitude, src.ins().latitude)


def test_writer_atomic_on_exception(tmp_path: Path, real_labels_path: Path) -> None:
    out = tmp_path / "seq"
    raw = load_labels(real_labels_path).raw
    with pytest.raises(RuntimeError, match="boom"), SequenceWriter(out, raw) as w:
        w.write_image("/rgb_center/012_1631441453.300000000.png", np.zeros((4, 4, 3), np.uint8))
        assert w.partial.is_dir()
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_incomplete_stream(tmp_path: Path, real_labels_path: Path) -> None:
    out = tmp_path / "seq"
    raw = load_labels(real_labels_path).raw
    with pytest.raises(SequenceError, match="not written"), SequenceWriter(out, raw) as w:
        w.write_image("/rgb_center/012_1631441453.300000000.png", np.zeros((4, 4, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileExistsError):
        tmp_path.joinpath("exists").mkdir()
        SequenceWriter(tmp_path / "exists", raw)
