"""app/core/db.py: the schema created by processes that start together on a new database.

Another process's statement is played by the sqlite3 module on the same file, run just before the engine's own
statement, where a process starting at the same time would have run it."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterator

import pytest
from sqlalchemy import Engine, event, inspect
from sqlalchemy.exc import OperationalError

from app.core import db, jobstore
from app.core.settings import Settings

SCENE = "a" * 32


@pytest.fixture
def settings(tmp_path) -> Iterator[Settings]:
    db._engines.clear()  # each test opens its database as a new process would
    yield Settings(data_dir=tmp_path / "data")
    db._engines.clear()


@pytest.fixture
def before_statements() -> Iterator[Callable]:
    """``hook(rewrite)``: ``rewrite(statement) -> statement`` runs before every statement of every engine."""
    hooks = []

    def add(rewrite: Callable[[str], str]) -> None:
        def hook(conn, cursor, statement, parameters, context, executemany):
            return rewrite(statement), parameters

        event.listen(Engine, "before_cursor_execute", hook, retval=True)
        hooks.append(hook)

    yield add
    for hook in hooks:
        event.remove(Engine, "before_cursor_execute", hook)


def _database(settings: Settings) -> str:
    return str(settings.data_dir / "voxnerf.sqlite")


def _other_process_first(settings: Settings, prefix: str, seen: list[str]) -> Callable[[str], str]:
    """A rewrite that lets "another process" run the first statement starting with ``prefix`` on the database
    just before the engine runs it; every such statement is appended to ``seen``."""

    def rewrite(statement: str) -> str:
        if statement.strip().startswith(prefix):
            seen.append(statement)
            if len(seen) == 1:
                with sqlite3.connect(_database(settings)) as conn:
                    conn.execute(statement)
        return statement

    return rewrite


def test_a_table_another_process_created_meanwhile_is_taken_as_created(settings, before_statements):
    """The race ``voxnerf serve`` lost on a busy machine: its API found no scenes table, a worker created it, and the
    API's CREATE TABLE failed ("table scenes already exists"), so the API did not start."""
    creates = []
    before_statements(_other_process_first(settings, "CREATE TABLE scenes", creates))
    engine = db.get_engine(settings)
    assert len(creates) == 1  # the second attempt found the table and created the others
    assert {"scenes", "jobs"} <= set(inspect(engine).get_table_names())
    jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
    assert jobstore.create_job(settings, SCENE, {"max_iters": 5}).state == "queued"


def test_a_column_another_process_added_meanwhile_is_taken_as_added(settings, before_statements, tmp_path):
    """Two processes opening a database of an earlier version both add its missing column: the second one's
    ALTER TABLE fails ("duplicate column name") and its next attempt finds the column."""
    jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    with sqlite3.connect(_database(settings)) as conn:
        conn.execute("ALTER TABLE jobs DROP COLUMN loss_series")
    db._engines.clear()
    alters = []
    before_statements(_other_process_first(settings, 'ALTER TABLE "jobs" ADD COLUMN "loss_series"', alters))
    engine = db.get_engine(settings)
    assert len(alters) == 1
    assert "loss_series" in {c["name"] for c in inspect(engine).get_columns("jobs")}
    assert jobstore.JOBS.get(settings, job.id).loss_series is None


def test_an_error_that_persists_is_raised_after_the_last_attempt(settings, before_statements):
    """A failure no other process explains (here every CREATE TABLE of the scenes table is refused) is raised,
    after ``SCHEMA_ATTEMPTS`` tries, and no engine is kept for the process."""
    creates = []

    def refuse(statement: str) -> str:
        if statement.strip().startswith("CREATE TABLE scenes"):
            creates.append(statement)
            return "CREATE TABLE scenes (id"  # a syntax error: sqlite3.OperationalError, as a refusal would be
        return statement

    before_statements(refuse)
    with pytest.raises(OperationalError):
        db.get_engine(settings)
    assert len(creates) == db.SCHEMA_ATTEMPTS
    assert not db._engines
