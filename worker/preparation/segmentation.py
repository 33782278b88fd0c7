"""Semantic segmentation of camera frames with an ONNX model (onnxruntime).

The paper ran DDRNet trained on RailSem19. Those weights cannot be downloaded here: users
supply their own ``.onnx`` file. The model takes one NCHW float32 image, normalised as
``(rgb / 255 - mean) / std``, and returns either per-class logits ``(1, C, h, w)`` or
labels ``(1, h, w)`` / ``(h, w)``; outputs smaller than the image (DDRNet gives 1/8) are
brought back to the image size (argmax first, then nearest-neighbour).

The default class map is RailSem19's 19 semantic classes (rs19-config.json order).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence as Seq
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

log = logging.getLogger(__name__)

#: RailSem19 semantic classes, index = label id.
RAILSEM19_CLASSES: tuple[str, ...] = (
    "road",
    "sidewalk",
    "construction",
    "tram-track",
    "fence",
    "pole",
    "traffic-light",
    "traffic-sign",
    "vegetation",
    "terrain",
    "sky",
    "human",
    "rail-track",
    "car",
    "truck",
    "trackbed",
    "on-rails",
    "rail-raised",
    "rail-embedded",
)
#: The classes that are rails themselves (RailSem19's rail-track is the area between).
DEFAULT_RAIL_CLASSES: tuple[str, ...] = ("rail-raised", "rail-embedded")
IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)


class SegmentationModel:
    """An ONNX semantic segmentation model run with onnxruntime.

    Parameters
    ----------
    path : the ``.onnx`` file.
    input_size : (height, width) the image is resized to, or None: the model's fixed
        input size if it has one, else the image's own size.
    mean, std : per-channel normalisation of RGB in [0, 1].
    class_map : class names by label id (default RailSem19's 19).
    rail_classes : names (or ids) of the classes that are rails.
    threads : intra-op threads of onnxruntime (None: its default).
    """

    def __init__(
        self,
        path: str | Path,
        input_size: tuple[int, int] | None = None,
        mean: Seq[float] = IMAGENET_MEAN,
        std: Seq[float] = IMAGENET_STD,
        class_map: Seq[str] = RAILSEM19_CLASSES,
        rail_classes: Seq[str | int] = DEFAULT_RAIL_CLASSES,
        threads: int | None = None,
    ) -> None:

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"segmentation model not found: {self.path}")
        self.mean = np.asarray(mean, dtype=np.float32).reshape(3)
        self.std = np.asarray(std, dtype=np.float32).reshape(3)
        if np.any(self.std <= 0):
            raise ValueError("std must be positive")
        self.class_map = tuple(str(c) for c in class_map)
        ids = []
        for c in rail_classes:
            if isinstance(c, (int, np.integer)):
                ids.append(int(c))
            elif c in self.class_map:
                ids.append(self.class_map.index(c))
            else:
                raise ValueError(f"rail class {c!r} is not in the class map")
        self.rail_ids = np.array(sorted(set(ids)), dtype=np.int64)
        so = ort.SessionOptions()
        if threads:
            so.intra_op_num_threads = int(threads)
        self.session = ort.InferenceSession(str(self.path), so, providers=["CPUExecutionProvider"])
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        shape = list(inp.shape)
        if input_size is None and len(shape) == 4 and all(isinstance(d, int) for d in shape[2:]):
            input_size = (int(shape[2]), int(shape[3]))
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))

    @classmethod
    def from_config(cls, cfg: dict[str, Any] | SegmentationModel) -> SegmentationModel:
        """From a dict with the constructor's arguments (``path`` required)."""
        if isinstance(cfg, SegmentationModel):
            return cfg
        cfg = dict(cfg)
        if "path" not in cfg:
            raise ValueError("segmentation model config needs 'path'")
        return cls(**cfg)

    def to_config(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "input_size": self.input_size,
            "mean": self.mean.tolist(),
            "std": self.std.tolist(),
            "class_map": list(self.class_map),
            "rail_classes": [int(i) for i in self.rail_ids],
        }

    def preprocess(self, rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
        """(H, W, 3) uint8 RGB (or grey (H, W)) -> (1, 3, h, w) float32 normalised."""
        img = np.asarray(rgb)
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        img = img[:, :, :3]
        if self.input_size is not None and img.shape[:2] != self.input_size:
            h, w = self.input_size
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_LINEAR)
        x = (img.astype(np.float32) / 255.0 - self.mean) / self.std
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

    def predict(self, rgb: NDArray[np.uint8]) -> NDArray[np.int64]:
        """Label id per pixel of the input image, (H, W) int64."""
        H, W = np.asarray(rgb).shape[:2]
        out = np.asarray(self.session.run(None, {self.input_name: self.preprocess(rgb)})[0])
        if out.ndim == 4:
            if out.shape[1] == 1 and not np.issubdtype(out.dtype, np.floating):
                labels = out[0, 0]
            else:
                labels = np.argmax(out[0], axis=0)
        elif out.ndim == 3:
            labels = out[0]
        elif out.ndim == 2:
            labels = out
        else:
            raise ValueError(f"unexpected segmentation output shape {out.shape}")
        labels = labels.astype(np.int32)
        if labels.shape != (H, W):
            labels = cv2.resize(labels, (W, H), interpolation=cv2.INTER_NEAREST)
        return labels.astype(np.int64)

    def rail_mask(self, rgb: NDArray[np.uint8]) -> NDArray[np.bool_]:
        """(H, W) bool: pixels of a rail class."""
        return np.isin(self.predict(rgb), self.rail_ids)
