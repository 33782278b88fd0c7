"""Engine and sessions from the settings.

SQLite (the embedded default) gets WAL, a busy timeout and foreign keys on every
connection, so the API and a worker process can share the file. PostgreSQL gets a
pre-pinged pool. ``session_scope()`` is the one way short-lived code (workers, CLI) opens
a transaction; the API uses a session per request (``service.deps``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any, cast

from sqlalchemy import CursorResult, Engine, Update, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from osdar_platform.settings import Settings, get_settings

SQLITE_BUSY_TIMEOUT_MS = 30_000


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()


def make_engine(url: str, **kwargs: Any) -> Engine:
    """An engine for ``url`` with the per-backend settings above."""
    u = make_url(url)
    if u.get_backend_name() == "sqlite":
        engine = create_engine(
            u,
            connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000},
            **kwargs,
        )
        event.listen(engine, "connect", _sqlite_pragmas)
        if u.database and u.database != ":memory:":
            folder = Path(u.database).parent

            @event.listens_for(engine, "do_connect")
            def _mkdir(*_args: Any) -> None:  # the folder appears with the first connection
                folder.mkdir(parents=True, exist_ok=True)

        return engine
    if u.drivername in ("postgresql", "postgres"):
        u = u.set(drivername="postgresql+psycopg")  # psycopg 3 is the driver we ship
    kwargs.setdefault("pool_pre_ping", True)
    kwargs.setdefault("pool_size", 10)
    kwargs.setdefault("max_overflow", 20)
    return create_engine(u, **kwargs)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(bind=engine, expire_on_commit=False)


@lru_cache(maxsize=4)
def _engine_for(url: str) -> Engine:
    return make_engine(url)


def get_engine(settings: Settings | None = None) -> Engine:
    """The process-wide engine for ``settings.database_url`` (created once per URL)."""
    settings = settings or get_settings()
    return _engine_for(str(settings.database_url))


def get_sessionmaker(settings: Settings | None = None) -> sessionmaker[Session]:
    return make_sessionmaker(get_engine(settings))


@contextmanager
def session_scope(settings: Settings | None = None) -> Iterator[Session]:
    """A session in one transaction: committed on success, rolled back on error."""
    session = get_sessionmaker(settings)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def updated_rows(session: Session, statement: Update) -> int:
    """Execute an UPDATE in ``session``; the number of rows it matched.

    ``Session.execute`` is typed as returning a ``Result``; an UPDATE's is a
    ``CursorResult``, the one that carries ``rowcount``.
    """
    return cast(CursorResult[Any], session.execute(statement)).rowcount
