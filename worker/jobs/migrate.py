"""Run the Alembic migrations (``osdar-ar migrate``, the prestart step, the tests)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"


def alembic_config(*, database_url: str | None = None, connection: Any = None) -> Any:
    """An Alembic Config on ``migrations/`` with the URL (or an open connection)."""
    from alembic.config import Config

    if not (MIGRATIONS_DIR / "env.py").is_file():
        raise FileNotFoundError(f"migrations not found at {MIGRATIONS_DIR}")
    cfg = Config()
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
    from alembic import command

    command.upgrade(alembic_config(database_url=database_url, connection=connection), revision)


def current_head() -> str:
    from alembic.script import ScriptDirectory

    return str(ScriptDirectory.from_config(alembic_config()).get_current_head())


def downgrade(*, database_url: str | None = None, revision: str = "base") -> None:
    """``alembic downgrade <revision>`` (tests; rolling back a release)."""
    from alembic import command

    command.downgrade(alembic_config(database_url=database_url), revision)
