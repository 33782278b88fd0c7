"""Where the shared reference data lives: ``../shared`` beside the checkout by default.

The folder holds the real OSDaR23 labels file (the real calibration the synthetic generator
and the tests use) and the OpenLABEL schema. A checkout elsewhere (a container, a clone in
/tmp) points at it with the ``OSDAR_AR_SHARED`` environment variable.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Environment variable naming the shared folder (overrides ``<checkout>/../shared``).
SHARED_ENV = "OSDAR_AR_SHARED"


def project_root() -> Path:
    """The folder that holds pyproject.toml (the checkout)."""
    return Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The shared folder: ``$OSDAR_AR_SHARED`` if set, else ``<checkout>/../shared``."""
    env = os.environ.get(SHARED_ENV, "").strip()
    return Path(env).expanduser() if env else project_root().parent / "shared"


def real_labels_path() -> Path:
    """The real OSDaR23 labels file of sequence 1_calibration_1.1 (the real calibration)."""
    return shared_dir() / "data/osdar23/1_calibration_1.1_labels.json"


def openlabel_schema_path() -> Path:
    """The ASAM OpenLABEL 1.0.0 JSON schema."""
    return shared_dir() / "data/osdar23/openlabel_v1_schema.json"
