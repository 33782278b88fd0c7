"""KISS-ICP in a child process, fed one frame at a time over pipes.

kiss-icp's Python binding keeps the GIL while it registers a frame (measured: a second
thread of the same process stalls for up to 90 ms per call), so no thread of ours can
read and split the next cloud meanwhile. A child process can: while it registers frame k,
the preparation reads frame k + 1, splits off its ground and computes the information
check of frame k - 1 (``localization.odometry.run_kiss_icp``). The child runs the same
KISS-ICP with the same settings on the same float64 points, so its poses are those of an
in-process run. The module imports numpy and kiss_icp only (the child starts in 0.5 s).

A plain ``subprocess`` (not ``multiprocessing``): Celery's prefork workers are daemonic
processes, which ``multiprocessing`` forbids to have children.

Protocol on the child's stdin / stdout (native byte order, the child is on the same host):

- parent -> child: ``uint64 n`` then ``n * 3`` float64 base points; ``n = 0`` means "no
  usable cloud: predict at constant velocity". End of input ends the child.
- child -> parent: 16 float64 (``T_odom_base`` of that frame, row-major), ``uint64 m`` and
  ``m * 3`` float64 (the points KISS-ICP registered, its ``source``).
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from typing import IO, Any

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
from numpy.typing import NDArray

F64 = NDArray[np.float64]

_COUNT = struct.Struct("=Q")


class KissProcessError(RuntimeError):
    """The child process could not start, or died, or broke the protocol."""


def _read_exact(stream: IO[bytes], n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            raise KissProcessError(f"KISS-ICP process closed its output ({len(buf)}/{n} bytes)")
        buf += chunk
    return bytes(buf)


class KissProcess:
    """A KISS-ICP child process with the :func:`kiss_config` of ``settings``.

    Use as a context manager (the child is ended on exit); :meth:`send` a frame, then
    :meth:`receive` its result before sending the next one.
    """

    def __init__(self, settings: dict[str, Any]) -> None:
        cmd = [sys.executable, "-m", __name__, json.dumps(settings)]
        try:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        except OSError as exc:
            raise KissProcessError(f"cannot start the KISS-ICP process: {exc}") from exc

    def __enter__(self) -> KissProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def send(self, points: F64, prior_t: F64 | None = None) -> None:
        """Queue one frame's (n, 3) base points (n = 0: constant-velocity prediction) and
        the expected step's translation (3,) in the previous frame's base (None: KISS-ICP's
        own constant-velocity guess)."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        prior = np.full(3, np.nan) if prior_t is None else np.asarray(prior_t, dtype=np.float64)
        try:
            assert self.proc.stdin is not None
            self.proc.stdin.write(_COUNT.pack(len(p)))
            self.proc.stdin.write(np.ascontiguousarray(prior).tobytes())
            if len(p):
                self.proc.stdin.write(memoryview(p).cast("B"))
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError) as exc:
            raise KissProcessError(f"KISS-ICP process gone ({self._status()})") from exc

    def receive(self) -> tuple[F64, F64]:
        """(T_odom_base (4, 4), source (m, 3)) of the frame sent last."""
        assert self.proc.stdout is not None
        try:
            T = np.frombuffer(_read_exact(self.proc.stdout, 16 * 8), dtype=np.float64)
            (m,) = _COUNT.unpack(_read_exact(self.proc.stdout, _COUNT.size))
            src = np.frombuffer(_read_exact(self.proc.stdout, int(m) * 24), dtype=np.float64)
        except KissProcessError as exc:
            raise KissProcessError(f"{exc}; {self._status()}") from exc
        return T.reshape(4, 4).copy(), src.reshape(-1, 3).copy()

    def _status(self) -> str:
        code = self.proc.poll()
        return "still running" if code is None else f"exit code {code}"

    def close(self) -> None:
        """End the child (closing its input ends it; killed if it does not end)."""
        try:
            if self.proc.stdin is not None and not self.proc.stdin.closed:
                self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()


#: Frames waiting for the map beyond this many are added anyway (a standing train: its
#: frames are all at one pose, the queue would grow without end).
MAX_PENDING_FRAMES = 50


class LaggedKissICP(KissICP):  # type: ignore[misc]
    """KISS-ICP whose local map takes a frame only once the train has moved ``map_lag_m``
    from it.

    A spinning lidar samples the scene in the same pattern every revolution, fixed in the
    base frame. When a frame is registered against a map holding the frame before, taken
    from nearly the same pose, each point's nearest map point is the same beam's return of
    that frame, which pulls point-to-point ICP towards the previous pose's pattern rather
    than the surfaces. At 15 cm steps and 30 % density that bias turned the heading about
    30 mdeg every frame, the same way every frame (tight_curve and station at 1.5 m/s:
    -577 and -909 mdeg over 20 and 35 frames, 2 mdeg true turn; registering against the
    true map of the previous frame alone gave -9 cm of the 15 cm step along the track,
    against frames more than 1 m back 1 cm). Keeping the frames of the last ``map_lag_m``
    out of the map leaves only samples from other viewpoints; a frame enters once the
    predicted pose of the frame being registered is ``map_lag_m`` from it. Only while the
    train is slow: once the predicted step is ``fast_step_m`` or more, every frame enters
    before the next one registers (KISS-ICP's own map; on dense clouds at 0.6 m a frame
    withholding the previous frame cost fused 0.6-0.8 px of anchor error).
    ``map_lag_m = 0``: KISS-ICP as is. The first frame enters at once (the map is never
    empty after it); a standing train's frames enter :data:`MAX_PENDING_FRAMES` late.
    """

    def __init__(
        self, config: KISSConfig, map_lag_m: float = 0.0, fast_step_m: float = np.inf
    ) -> None:
        super().__init__(config)
        self.map_lag_m = float(map_lag_m)
        self.fast_step_m = float(fast_step_m)
        self.pending: list[tuple[F64, F64]] = []  # (frame points, T_odom_base) in order

    def _update_map(self, T_odom_next: F64) -> None:
        """Add the pending frames at least ``map_lag_m`` from ``T_odom_next`` (4, 4), all
        of them when the predicted step (``last_delta``) is ``fast_step_m`` or more."""
        step = float(np.linalg.norm(np.asarray(self.last_delta)[:3, 3]))
        lag = 0.0 if step >= self.fast_step_m else self.map_lag_m
        while self.pending:
            points, T_odom_base = self.pending[0]
            far = np.linalg.norm(T_odom_base[:3, 3] - T_odom_next[:3, 3]) >= lag
            if not (far or self.local_map.empty() or len(self.pending) > MAX_PENDING_FRAMES):
                return
            self.local_map.update(points, T_odom_base)
            self.pending.pop(0)

    def register_frame(self, frame: F64, timestamps: F64) -> tuple[F64, F64]:
        """KISS-ICP's ``register_frame`` with the lagged map update."""
        frame = self.preprocessor.preprocess(frame, timestamps, self.last_delta)
        source, frame_downsample = self.voxelize(frame)
        sigma = self.adaptive_threshold.get_threshold()
        initial_guess = self.last_pose @ self.last_delta
        self._update_map(initial_guess)
        new_pose = self.registration.align_points_to_map(
            points=source,
            voxel_map=self.local_map,
            initial_guess=initial_guess,
            max_correspondance_distance=3 * sigma,
            kernel=sigma,
        )
        self.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
        self.pending.append((frame_downsample, new_pose))
        if self.map_lag_m <= 0.0:
            self._update_map(new_pose)  # KISS-ICP's order (same map at the next frame)
        self.last_delta = np.linalg.inv(self.last_pose) @ new_pose
        self.last_pose = new_pose
        return frame, source


def make_kiss(settings: dict[str, Any]) -> LaggedKissICP:
    """The KISS-ICP of the settings (:func:`kiss_config`; ``map_lag_m``, default 0, and
    ``map_fast_step_m``, default none: see :class:`LaggedKissICP`)."""
    return LaggedKissICP(
        kiss_config(settings),
        float(settings.get("map_lag_m", 0.0)),
        float(settings.get("map_fast_step_m", np.inf)),
    )


def kiss_config(settings: dict[str, Any]) -> Any:
    """A KISSConfig from the settings (keys deskew, max_range, min_range, voxel_size,
    max_num_threads: what the preparation sets, see ``odometry._kiss_settings``; its
    map_lag_m and map_fast_step_m are :func:`make_kiss`'s)."""

    cfg = KISSConfig()
    cfg.data.deskew = bool(settings["deskew"])
    cfg.data.max_range = float(settings["max_range"])
    cfg.data.min_range = float(settings["min_range"])
    cfg.mapping.voxel_size = float(settings["voxel_size"])
    cfg.registration.max_num_threads = int(settings["max_num_threads"])
    return cfg


def set_prior(kiss: Any, prior_t: F64 | None) -> None:
    """Seed KISS-ICP's next initial guess with an expected step translation (3,) in the
    previous frame's base (its rotation stays KISS-ICP's constant-velocity one). Non-finite
    or None: KISS-ICP's own guess.

    From a standing start KISS-ICP's constant-velocity guess is zero, and against its 1 m
    map voxels a slow train's 15 cm steps came out at 6-12 cm for a second or more
    (tight_curve at 1.5 m/s, 30 % density: 2.0 m travelled against 2.85 m).
    """
    if prior_t is None or not np.all(np.isfinite(prior_t)):
        return
    delta = np.array(kiss.last_delta, dtype=np.float64)
    delta[:3, 3] = prior_t
    kiss.last_delta = delta


def serve(settings: dict[str, Any], inp: IO[bytes], out: IO[bytes]) -> None:
    """The child's loop: register every frame read from ``inp``, answer on ``out``."""

    kiss = make_kiss(settings)
    while True:
        head = inp.read(_COUNT.size)
        if len(head) < _COUNT.size:
            return
        (n,) = _COUNT.unpack(head)
        prior = np.frombuffer(_read_exact(inp, 24), dtype=np.float64)
        p = np.frombuffer(_read_exact(inp, int(n) * 24), dtype=np.float64).reshape(-1, 3)
        set_prior(kiss, prior)
        if n == 0:
            kiss.last_pose = kiss.last_pose @ kiss.last_delta
            source = np.zeros((0, 3))
        else:
            _, source = kiss.register_frame(p.copy(), np.zeros(len(p)))
        src = np.ascontiguousarray(source, dtype=np.float64).reshape(-1, 3)
        out.write(np.ascontiguousarray(kiss.last_pose, dtype=np.float64).tobytes())
        out.write(_COUNT.pack(len(src)))
        out.write(src.tobytes())
        out.flush()


if __name__ == "__main__":
    serve(json.loads(sys.argv[1]), sys.stdin.buffer, sys.stdout.buffer)
