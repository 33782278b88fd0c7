"""Alembic environment: the URL comes from the settings, never from alembic.ini.

``config.attributes`` may carry ``connection`` (run on an open connection, e.g. inside a
test's schema) or ``database_url`` (set by ``osdar_platform.migrate.upgrade``).
"""

from __future__ import annotations

import logging

from alembic import context

from osdar_platform.db import make_engine
from osdar_platform.models import Base
from osdar_platform.settings import get_settings

config = context.config
target_metadata = Base.metadata
log = logging.getLogger("alembic.env")


def _url() -> str:
    url = config.attributes.get("database_url")
    if url:
        return str(url)
    return str(get_settings().database_url)


def run_migrations_offline() -> None:
    context.configure(
        url=_url(),
        target_metadata=target_metadata,
        literal_binds=True,
        dialect_opts={"paramstyle": "named"},
        render_as_batch=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def _run(connection) -> None:  # type: ignore[no-untyped-def]
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",  # ALTER on SQLite
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = make_engine(_url())
    try:
        with engine.connect() as conn:
            _run(conn)
            conn.commit()
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
