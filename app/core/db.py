"""Database engine and sessions, safe to use from the API, from Celery's forked workers and from threads.

SQLite (the embedded default) runs in WAL mode with a busy timeout, so one writer and many readers in
several processes do not block each other. An engine is created per process: a forked worker never
reuses its parent's connections. Processes that start together on a new database (``voxnerf serve``'s API and
workers) each create the schema; :func:`create_schema` lets them.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import Engine, create_engine, event, inspect, make_url, text
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from app.core.models import Base
from app.core.progress import NULL_READS_AS_DEFAULT
from app.core.settings import Settings

SQLITE_BUSY_TIMEOUT_MS = 30_000
SCHEMA_ATTEMPTS = 5

_lock = threading.Lock()
_engines: dict[tuple[int, str], tuple[Engine, sessionmaker[Session]]] = {}


def _configure_sqlite(dbapi_connection, _record) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def _engine_and_factory(settings: Settings) -> tuple[Engine, sessionmaker[Session]]:
    url = settings.sqlalchemy_url
    key = (os.getpid(), url)
    with _lock:
        if key not in _engines:
            if url.startswith("sqlite"):
                settings.data_dir.mkdir(parents=True, exist_ok=True)
                engine = create_engine(
                    url, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000, "check_same_thread": False}
                )
                event.listen(engine, "connect", _configure_sqlite)
            else:
                engine = create_engine(url, pool_pre_ping=True)
            create_schema(engine)
            _engines[key] = (engine, sessionmaker(engine, expire_on_commit=False))
        return _engines[key]


def create_schema(engine: Engine) -> None:
    """Create the missing tables, then the missing columns (:func:`add_missing_columns`). Both check what exists,
    then create: a process starting at the same time (the API and the workers of ``voxnerf serve`` on a new data
    directory) can create a table or column between one's check and its statement, which then fails ("table
    already exists", "duplicate column"). Such a failed attempt is made again, up to ``SCHEMA_ATTEMPTS`` in all,
    and the next check finds what the other process created; an error that persists is raised."""
    for attempt in range(1, SCHEMA_ATTEMPTS + 1):
        try:
            Base.metadata.create_all(engine)
            add_missing_columns(engine)
            return
        except DBAPIError:
            if attempt == SCHEMA_ATTEMPTS:
                raise


def add_missing_columns(engine: Engine) -> list[str]:
    """Add to existing tables the columns the models have gained since the tables were created (``create_all``
    creates missing tables only), so a database written by an earlier version keeps working; returns
    ``table.column`` of each column added. Only columns whose old rows may hold null are added (nullable ones,
    and those marked ``NULL_READS_AS_DEFAULT``, such as the progress fields); any other missing column is a
    RuntimeError: it needs a migration of its own."""
    added = []
    existing = inspect(engine)
    for table in Base.metadata.sorted_tables:
        if not existing.has_table(table.name):
            continue
        present = {column["name"] for column in existing.get_columns(table.name)}
        for column in table.columns:
            if column.name in present:
                continue
            if not (column.nullable or column.info.get(NULL_READS_AS_DEFAULT)):
                raise RuntimeError(f"table {table.name} lacks the non-null column {column.name}: migrate it")
            kind = column.type.compile(dialect=engine.dialect)
            with engine.begin() as conn:
                conn.execute(text(f'ALTER TABLE "{table.name}" ADD COLUMN "{column.name}" {kind}'))
            added.append(f"{table.name}.{column.name}")
    return added


def may_hold_rows(settings: Settings) -> bool:
    """False when the job store is a SQLite file that does not exist yet (nothing was ever written, and asking
    it would create it); True otherwise (a server database must be asked)."""
    url = make_url(settings.sqlalchemy_url)
    if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
        return True
    return Path(url.database).exists()


def get_engine(settings: Settings) -> Engine:
    """This process's engine for ``settings.sqlalchemy_url``; creates the tables on first use."""
    return _engine_and_factory(settings)[0]


@contextmanager
def session_scope(settings: Settings) -> Iterator[Session]:
    """A session committed on success and rolled back on error. Loaded rows stay usable after it closes."""
    session = _engine_and_factory(settings)[1]()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def ping(settings: Settings) -> None:
    """Raise if the database cannot answer ``SELECT 1``."""
    with get_engine(settings).connect() as conn:
        conn.execute(text("SELECT 1"))
