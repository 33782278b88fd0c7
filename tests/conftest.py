"""Shared fixtures: the real OSDaR23 labels file and tiny OSDaR23-layout sequences."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from osdar_platform.shared_data import SHARED_ENV, shared_dir
from osdar_platform.shared_data import real_labels_path as _shared_labels

REAL_LABELS = _shared_labels()


def pytest_sessionstart(session: pytest.Session) -> None:
    """Most tests generate synthetic sequences from the real calibration: without the
    shared folder they would fail by the hundred, so stop at once and say what to do."""
    if not REAL_LABELS.is_file():
        pytest.exit(
            f"the real OSDaR23 labels file {REAL_LABELS} is missing: the tests need the "
            f"shared folder ({shared_dir()}) beside the checkout, or {SHARED_ENV}=/path/to/shared",
            returncode=2,
        )


@pytest.fixture(scope="session")
def real_labels_path() -> Path:
    """The unmodified labels file of OSDaR23 sequence 1_calibration_1.1 (read-only)."""
    if not REAL_LABELS.is_file():
        pytest.skip(f"{REAL_LABELS} not available")
    return REAL_LABELS


@pytest.fixture(scope="session")
def _real_raw(real_labels_path: Path) -> dict:
    return json.loads(real_labels_path.read_bytes())


@pytest.fixture
def tiny_sequence(tmp_path: Path, _real_raw: dict) -> Callable[..., Path]:
    """Factory: ``make(frames=(12, 13, 14), name="tiny_1.1", pcd_data="binary")`` -> folder.

    The labels are the real file's metadata, calibration and frame properties (real uris
    and timestamps) for the chosen frames, without annotations. Files are written for
    ``rgb_center`` (RGB 12x16), ``ir_center`` (grey), ``lidar`` (40 points) and the three
    NovAtel folders; the other streams stay calibration-only.
    """
    from worker.osdar import dump_labels, write_ins_folder, write_pcd, write_png
    from worker.osdar.ins_tables import CorrImu, InsPva, InsStdDev
    from worker.osdar.pcd import PointCloud

    def make(frames=(12, 13, 14), name="tiny_1.1", pcd_data="binary") -> Path:
        rng = np.random.default_rng(7)
        folder = tmp_path / name
        ol = copy.deepcopy(_real_raw["openlabel"])
        ol["objects"] = {}
        ol["frames"] = {
            str(i): {"frame_properties": ol["frames"][str(i)]["frame_properties"]} for i in frames
        }
        ol["frame_intervals"] = [{"frame_start": frames[0], "frame_end": frames[-1]}]
        dump_labels({"openlabel": ol}, folder / f"{name}_labels.json")
        ins_names = []
        for i in frames:
            streams = ol["frames"][str(i)]["frame_properties"]["streams"]
            write_png(
                folder / streams["rgb_center"]["uri"][1:],
                rng.integers(0, 255, (12, 16, 3), dtype=np.uint8),
            )
            write_png(
                folder / streams["ir_center"]["uri"][1:],
                rng.integers(0, 255, (6, 8), dtype=np.uint8),
            )
            t = float(streams["lidar"]["stream_properties"]["sync"]["timestamp"])
            cloud = {
                **{
                    k: rng.normal(0, 20, 40).astype(np.float32)
                    for k in ("x", "y", "z", "intensity")
                },
                "timestamp": t - rng.uniform(0, 0.1, 40),
                "sensor_index": rng.integers(0, 6, 40).astype(np.uint8),
            }
            write_pcd(folder / streams["lidar"]["uri"][1:], PointCloud(cloud), data=pcd_data)
            ins_names.append(f"{i:03d}_{ol['frames'][str(i)]['frame_properties']['timestamp']}.csv")
        n = len(frames)
        for folder_name, cls in (
            ("novatel_oem7_inspva", InsPva),
            ("novatel_oem7_insstdev", InsStdDev),
            ("novatel_oem7_corrimu", CorrImu),
        ):
            cols = {c: rng.normal(size=n) for c in cls.columns()}
            cols["frame_idx"] = np.asarray(frames, dtype=np.int64)
            cols["timestamp"] = np.array([float(s.split("_")[1][:-4]) for s in ins_names])
            if "gps_week_number" in cols:
                cols["gps_week_number"] = np.full(n, 2174, dtype=np.int64)
            write_ins_folder(folder / folder_name, cls(**cols), ins_names)
        return folder

    return make


pytest_plugins = ["tests.conftest_service"]


@pytest.fixture
def fresh_data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An empty OSDAR_AR_DATA_DIR and no DATABASE_URL: the embedded SQLite default on a
    fresh database (settings re-read before and after)."""
    from osdar_platform.settings import get_settings

    for name in ("DATABASE_URL", "OSDAR_AR_DATABASE_URL"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OSDAR_AR_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    yield tmp_path
    get_settings.cache_clear()
