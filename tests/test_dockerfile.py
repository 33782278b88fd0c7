"""The image (Dockerfile) carries every package the project installs: a package left out
builds fine and fails only when the container imports it."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _packages() -> list[str]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    include = cfg["tool"]["setuptools"]["packages"]["find"]["include"]
    return sorted(p.rstrip("*") for p in include)


def test_every_installed_package_is_copied_into_the_image() -> None:
    docker = (ROOT / "Dockerfile").read_text()
    copied = set(re.findall(r"^COPY (\S+) \./\1\s*$", docker, flags=re.MULTILINE))
    stubbed = set(re.findall(r"(\w+)/__init__\.py", docker))
    packages = _packages()
    assert {"service", "worker", "renderer", "geometry", "osdar_platform"} <= set(packages)
    for pkg in packages:
        assert (ROOT / pkg / "__init__.py").is_file(), pkg
        assert pkg in copied, f"Dockerfile does not COPY {pkg}/"
        assert pkg in stubbed, f"Dockerfile's dependency layer lacks {pkg}/__init__.py"
