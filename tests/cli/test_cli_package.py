"""The ``osdar-ar`` dispatcher (worker/cli/__init__.py): building the parser imports no
library, every sub-command leads to a command module, and ``osdar-ar worker`` loads no
numpy before it sets the thread caps."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from worker.cli import build_parser

CLI = Path(__file__).resolve().parents[2] / "worker" / "cli"


def _loaded_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint('\\n'.join(sys.modules))"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return set(out.split())


def test_the_parser_imports_no_library() -> None:
    loaded = _loaded_after("import worker.cli\nworker.cli.build_parser()")
    project = {m for m in loaded if m.partition(".")[0] in ("worker", "geometry", "renderer")}
    assert all(m == "worker" or m.startswith("worker.cli") for m in project), sorted(project)
    heavy = {"numpy", "tqdm", "pydantic", "sqlalchemy", "osdar_platform", "service"}
    assert not heavy & {m.partition(".")[0] for m in loaded}


def test_the_worker_command_loads_no_numpy_before_its_thread_caps() -> None:
    assert "numpy" not in _loaded_after("import worker.cli.serve")


def test_every_sub_command_has_a_command_module() -> None:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    groups = {name: p.get_default("command_group") for name, p in sub.choices.items()}
    assert set(groups) >= {"synth", "info", "demo", "serve", "worker", "migrate", "keys"}
    for name, group in groups.items():
        assert group is not None and (CLI / f"{group}.py").is_file(), name


def test_augment_optics_flags_reach_the_spec() -> None:
    """``--exposure-ms`` / ``--aperture-mm`` set RenderSpec's optics; left out, the spec's
    assumed defaults (renderer/camera_optics.py) stay."""
    from renderer.camera_optics import APERTURE_M, EXPOSURE_S
    from worker.cli.augment import _augment_spec

    base = ["augment", "SEQ", "--object", "rock", "--place", "s=30", "--out", "OUT"]
    spec = _augment_spec(
        build_parser().parse_args([*base, "--exposure-ms", "0", "--aperture-mm", "6"])
    )
    assert spec.render.exposure_ms == 0.0 and spec.render.aperture_mm == 6.0
    spec = _augment_spec(build_parser().parse_args(base))
    assert spec.render.exposure_ms == 1000.0 * EXPOSURE_S
    assert spec.render.aperture_mm == 1000.0 * APERTURE_M
