"""The prepared sequence on disk: a versioned, content-keyed, atomically written folder.

Layout of an artifact folder (``ARTIFACT_VERSION`` 1)::

    poses.csv              frame_idx,timestamp,x,y,z,qx,qy,qz,qw: T_world_base of the chosen
                           strategy at each frame's lidar timestamp (ground_truth/poses.csv
                           format and frame)
    world.json             the world frame's origin {latitude, longitude, height}
                           (WGS84 deg, ellipsoidal m); axes East-North-Up there
    centrelines.json       [Centreline.to_json(), ...], ego first ("ego": true)
    planes.json            [Plane.to_json(), ...]: ground / platform polygons (+ edges)
    poles.json             [Pole.to_json(), ...]: pole boxes and top points
    calibration_point.json CalibrationPoint.to_json() (null xyz when none was found)
    summary.json           key, version, sequence, config, strategy health, tracks,
                           scene-element and calibration summaries, per-stage seconds
    cloud.npz              the registered cloud: xyz (n, 3) float64, frame_idx (n,) int32,
                           sensor_index (n,) uint8, intensity (n,) float32, rail_points
                           (m, 3) float64
    reference_poses/       ins.csv, odometry.csv: the raw INS and the KISS-ICP poses at
                           the same frames (for comparison tables)

The cache key is ``sha256(content_key, config_hash, clicks digest, ARTIFACT_VERSION,
PREPARATION_REVISION)``.
An artifact is written into a temporary sibling folder and renamed into place; under a
cache folder, an ``fcntl`` lock per key makes a second preparation of the same key wait
and then reuse the first one's result.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from geometry.geodesy import WorldFrame
from geometry.pose_uncertainty import PoseInformation
from geometry.poses import PoseTrack
from worker.preparation.calibration_point import CalibrationPoint
from worker.preparation.centreline import Centreline
from worker.preparation.registration import RegisteredCloud
from worker.preparation.scene_elements import Plane, Pole

log = logging.getLogger(__name__)

ARTIFACT_VERSION = 1
#: The pose track's information matrix (:class:`~geometry.pose_uncertainty.PoseInformation`).
INFORMATION_FILE = "pose_information.npz"
#: Revision of the preparation's results: bumped whenever a change of the code changes what
#: a preparation of the same sequence with the same config produces (a strategy's weights,
#: the centreline fit...), so that artifacts cached by an older release are not reused.
PREPARATION_REVISION = 14

FILES = (
    "poses.csv",
    "world.json",
    "centrelines.json",
    "planes.json",
    "poles.json",
    "calibration_point.json",
    "summary.json",
    "cloud.npz",
)


def cache_key(content_key: str, config_hash: str, clicks_digest: str | None = None) -> str:
    """sha256 hex over the sequence content, the config, the clicks, the layout version and
    the preparation revision."""
    text = (
        f"{content_key}\0{config_hash}\0{clicks_digest or ''}\0{ARTIFACT_VERSION}"
        f"\0{PREPARATION_REVISION}"
    )
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass
class PreparedSequence:
    """The result of preparation (pipeline step 2), in memory or read back from disk.

    track : T_world_base of the chosen strategy at each frame's lidar timestamp;
    references : other pose tracks at the same frames ("ins", "odometry");
    centrelines : every track found (ego first); planes, poles : scene elements;
    calibration : the calibration point (None if not computed);
    summary : the JSON summary (health, timings, ...); folder : where it is on disk.
    The registered cloud is loaded from ``cloud.npz`` on first access when read from disk.
    """

    key: str
    world: WorldFrame
    track: PoseTrack
    centrelines: list[Centreline]
    planes: list[Plane]
    poles: list[Pole]
    calibration: CalibrationPoint | None
    summary: dict[str, Any]
    references: dict[str, PoseTrack] = field(default_factory=dict)
    #: uncertainty of ``track`` (``pose_information.npz``; None: not known)
    information: PoseInformation | None = None
    #: frame counter -> its lidar timestamp exactly as the input wrote it (for poses.csv)
    timestamp_text: dict[int, str] = field(default_factory=dict)
    folder: Path | None = None
    _cloud: RegisteredCloud | None = None
    _rail_points: np.ndarray | None = None

    @property
    def ego(self) -> Centreline | None:
        return next((c for c in self.centrelines if c.ego), None)

    @property
    def strategy(self) -> str:
        return str(self.summary.get("strategy", ""))

    @cached_property
    def _npz(self) -> dict[str, np.ndarray]:
        if self.folder is None:
            raise ValueError("prepared sequence has neither a cloud nor a folder")
        with np.load(self.folder / "cloud.npz") as z:
            return {k: z[k] for k in z.files}

    @property
    def cloud(self) -> RegisteredCloud:
        if self._cloud is None:
            z = self._npz
            self._cloud = RegisteredCloud(
                z["xyz"].astype(np.float64),
                z["frame_idx"].astype(np.int32),
                z["sensor_index"].astype(np.uint8),
                z["intensity"].astype(np.float32),
            )
        return self._cloud

    @property
    def rail_points(self) -> np.ndarray:
        if self._rail_points is None:
            self._rail_points = self._npz["rail_points"].astype(np.float64).reshape(-1, 3)
        return self._rail_points


# ---------------------------------------------------------------------------- write
def _dump(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, indent=1, allow_nan=False))


def _save_cloud(path: Path, cloud: RegisteredCloud, rail_points: np.ndarray) -> None:
    """``np.savez``-compatible archive, stored uncompressed: float64 coordinates deflate by
    only ~15 % while compression costs about as much as the whole registration."""
    arrays = {
        "xyz": np.ascontiguousarray(cloud.xyz, dtype=np.float64),
        "frame_idx": np.ascontiguousarray(cloud.frame_idx, dtype=np.int32),
        "sensor_index": np.ascontiguousarray(cloud.sensor_index, dtype=np.uint8),
        "intensity": np.ascontiguousarray(cloud.intensity, dtype=np.float32),
        "rail_points": np.ascontiguousarray(rail_points, dtype=np.float64).reshape(-1, 3),
    }
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for name, a in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, a, allow_pickle=False)


def write_files(prepared: PreparedSequence, folder: Path) -> None:
    """Write every artifact file into an existing empty ``folder`` (not atomic)."""
    prepared.track.to_csv(folder / "poses.csv", timestamp_text=prepared.timestamp_text)
    _dump(folder / "world.json", prepared.world.to_json())
    _dump(folder / "centrelines.json", [c.to_json() for c in prepared.centrelines])
    _dump(folder / "planes.json", [p.to_json() for p in prepared.planes])
    _dump(folder / "poles.json", [p.to_json() for p in prepared.poles])
    cal = None if prepared.calibration is None else prepared.calibration.to_json()
    _dump(folder / "calibration_point.json", cal)
    rail = np.zeros((0, 3)) if prepared._rail_points is None else prepared._rail_points
    _save_cloud(folder / "cloud.npz", prepared.cloud, rail)
    if prepared.references:
        (folder / "reference_poses").mkdir()
        for name, tr in prepared.references.items():
            tr.to_csv(
                folder / "reference_poses" / f"{name}.csv", timestamp_text=prepared.timestamp_text
            )
    if prepared.information is not None:
        (folder / INFORMATION_FILE).write_bytes(prepared.information.to_npz_bytes())
    # summary last: its presence marks a complete artifact
    _dump(folder / "summary.json", {**prepared.summary, "key": prepared.key})


def write_artifact(prepared: PreparedSequence, folder: str | Path) -> Path:
    """Write ``prepared`` to ``folder`` atomically (temp sibling + rename); returns it.

    An existing folder is replaced (moved aside, then removed) once the new one is complete.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.tmp-", dir=folder.parent))
    try:
        write_files(prepared, tmp)
        _replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    prepared.folder = folder
    return folder


def copy_artifact(src: str | Path, dst: str | Path) -> Path:
    """Copy a complete artifact folder to ``dst`` atomically (replacing it)."""
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        return dst
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=dst.parent))
    try:
        shutil.copytree(src, tmp, dirs_exist_ok=True)
        _replace(tmp, dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dst


def _replace(tmp: Path, folder: Path) -> None:
    os.chmod(tmp, 0o755)
    if folder.exists():
        old = folder.with_name(f".{folder.name}.old-{os.getpid()}")
        os.replace(folder, old)
        os.replace(tmp, folder)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, folder)


# ---------------------------------------------------------------------------- read
def artifact_key(folder: str | Path) -> str | None:
    """The key of a complete artifact of this version in ``folder``, else None."""
    path = Path(folder) / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if summary.get("artifact_version") != ARTIFACT_VERSION:
        return None
    if not all((Path(folder) / name).is_file() for name in FILES):
        return None
    return summary.get("key")


def read_artifact(folder: str | Path) -> PreparedSequence:
    """Read an artifact folder (the cloud lazily). Raises ValueError if incomplete/old."""
    folder = Path(folder)
    key = artifact_key(folder)
    if key is None:
        raise ValueError(f"{folder}: not a complete version-{ARTIFACT_VERSION} artifact")
    summary = json.loads((folder / "summary.json").read_text())
    cal = json.loads((folder / "calibration_point.json").read_text())
    refs = {}
    ref_dir = folder / "reference_poses"
    if ref_dir.is_dir():
        refs = {p.stem: PoseTrack.from_csv(p) for p in sorted(ref_dir.glob("*.csv"))}
    info_file = folder / INFORMATION_FILE
    info = PoseInformation.from_npz_bytes(info_file.read_bytes()) if info_file.is_file() else None
    return PreparedSequence(
        key=key,
        information=info,
        world=WorldFrame.from_json(json.loads((folder / "world.json").read_text())),
        track=PoseTrack.from_csv(folder / "poses.csv"),
        centrelines=[
            Centreline.from_json(d) for d in json.loads((folder / "centrelines.json").read_text())
        ],
        planes=[Plane.from_json(d) for d in json.loads((folder / "planes.json").read_text())],
        poles=[Pole.from_json(d) for d in json.loads((folder / "poles.json").read_text())],
        calibration=None if cal is None else CalibrationPoint.from_json(cal),
        summary=summary,
        references=refs,
        folder=folder,
    )


# ---------------------------------------------------------------------------- cache
@contextlib.contextmanager
def key_lock(cache_dir: str | Path, key: str) -> Iterator[None]:
    """Exclusive ``fcntl`` lock of one key under ``cache_dir`` (blocks until free)."""
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with open(cache_dir / f"{key}.lock", "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def cached_folder(cache_dir: str | Path, key: str) -> Path:
    """Where the artifact of ``key`` lives under ``cache_dir``."""
    return Path(cache_dir) / key
