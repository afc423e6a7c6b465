"""Job-store tables (SQLAlchemy ORM). Times are UNIX seconds (float, UTC); JSON columns hold dicts/lists.

The job's progress columns (stage, iteration, progress, ETA, history, stages...) are not listed here: they are
built from the engine's ``ProgressEvent`` by :func:`app.core.progress.progress_columns`.
"""

from __future__ import annotations

from sqlalchemy import JSON, Boolean, Float, Integer, String, Text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from app.core.progress import progress_columns

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
ACTIVE_STATES = ("queued", "running")


class Base(DeclarativeBase):
    pass


class SceneRow(Base):
    """An uploaded, validated scene stored in ``<data_dir>/scenes/<id>``."""

    __tablename__ = "scenes"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(255))
    created_at: Mapped[float] = mapped_column(Float)
    size_bytes: Mapped[int] = mapped_column(Integer)
    summary: Mapped[dict] = mapped_column(JSON)


# A declarative mixin: its columns are copied into JobRow (one per stored ProgressEvent field).
ProgressColumns = type("ProgressColumns", (), progress_columns())


class JobRow(ProgressColumns, Base):
    """A training job and everything the API reports about it; the run lives in ``<data_dir>/runs/<id>``.

    Besides the columns below it has one column per field of :data:`app.core.progress.PROGRESS_FIELDS`.
    ``attempt`` is a fencing token: each claim by a worker increments it, and a worker writes only while the
    row still carries the attempt it claimed, so a worker presumed dead can never overwrite its successor.
    """

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    scene_id: Mapped[str] = mapped_column(String(32), index=True)
    state: Mapped[str] = mapped_column(String(16), index=True)
    options: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    metrics: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    requeues: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(String(255), nullable=True)
    heartbeat_at: Mapped[float | None] = mapped_column(Float, nullable=True)
