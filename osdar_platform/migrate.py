"""Run the Alembic migrations (``osdar-ar migrate``, the prestart step, the tests)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.script import ScriptDirectory

MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"


class _CurrentStdout:
    """A text stream that writes to whatever ``sys.stdout`` is when it is written to."""

    @property
    def encoding(self) -> str:
        return getattr(sys.stdout, "encoding", None) or "utf-8"

    def write(self, text: str) -> int:
        return sys.stdout.write(text)

    def flush(self) -> None:
        sys.stdout.flush()


def alembic_config(*, database_url: str | None = None, connection: Any = None) -> Any:
    """An Alembic Config on ``migrations/`` with the URL (or an open connection)."""

    if not (MIGRATIONS_DIR / "env.py").is_file():
        raise FileNotFoundError(f"migrations not found at {MIGRATIONS_DIR}")
    # Config's ``stdout`` defaults to the sys.stdout of the moment alembic.config was first
    # imported (a default argument): under pytest that can be a capture stream closed since,
    # and ``command.check`` then writes to a closed file. Resolve sys.stdout at write time.
    cfg = Config(stdout=_CurrentStdout())  # type: ignore[arg-type]
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.set_main_option("path_separator", "os")
    if database_url is not None:
        cfg.attributes["database_url"] = database_url
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def upgrade(
    *, database_url: str | None = None, connection: Any = None, revision: str = "head"
) -> None:
    """``alembic upgrade <revision>`` on ``database_url`` (default: the settings')."""

    command.upgrade(alembic_config(database_url=database_url, connection=connection), revision)


def current_head() -> str:

    return str(ScriptDirectory.from_config(alembic_config()).get_current_head())


def downgrade(*, database_url: str | None = None, revision: str = "base") -> None:
    """``alembic downgrade <revision>`` (tests; rolling back a release)."""

    command.downgrade(alembic_config(database_url=database_url), revision)
