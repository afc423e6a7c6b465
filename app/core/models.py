"""Job-store tables (SQLAlchemy ORM): scenes, training jobs, output jobs, capture imports, and the API's named
tokens. Times are UNIX seconds (float, UTC); JSON columns hold dicts/lists. ``created_by`` (and ``cancelled_by``)
name the principal that made (cancelled) a row (:class:`app.core.tokens.Principal`); null on rows written before
tokens existed.

The job's progress columns (stage, iteration, progress, ETA, history, stages...) are not listed here: they are
built from the engine's ``ProgressEvent`` by :func:`app.core.progress.progress_columns`.
"""

from __future__ import annotations

from sqlalchemy import JSON, Boolean, Float, Integer, String, Text, UniqueConstraint
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
    created_by: Mapped[str | None] = mapped_column(String(64), nullable=True)


class LeaseColumns:
    """The columns of a row on the lease lifecycle (:mod:`app.core.lease`), copied into each table of queued work:
    the cancel flag, ``attempt`` (the fencing token), ``requeues``, the claiming worker and its lease's
    ``heartbeat_at``; who queued the row (``created_by``, which per-principal queue limits count) and who cancelled
    it."""

    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    requeues: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(String(255), nullable=True)
    heartbeat_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    created_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    cancelled_by: Mapped[str | None] = mapped_column(String(64), nullable=True)


# A declarative mixin: its columns are copied into JobRow (one per stored ProgressEvent field).
ProgressColumns = type("ProgressColumns", (), progress_columns())


class JobRow(ProgressColumns, LeaseColumns, Base):
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
    callback_url: Mapped[str | None] = mapped_column(Text, nullable=True)  # webhooks: app/core/events.py


EVENT_KINDS = ("progress", "stage", "evaluation", "state")


class JobEventRow(Base):
    """One event of a training job's log (:mod:`app.core.events`), written in the transaction that changed the
    job: ``seq`` numbers the job's events from 1 and only grows; ``kind`` is one of :data:`EVENT_KINDS`;
    ``data`` the job's columns (``progress``, ``state``), the stage record (``stage``) or the history point
    (``evaluation``)."""

    __tablename__ = "job_events"
    __table_args__ = (UniqueConstraint("job_id", "seq"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    seq: Mapped[int] = mapped_column(Integer)
    kind: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float)


class WebhookDeliveryRow(Base):
    """The delivery of one ``state`` event of a job to its ``callback_url`` (:mod:`app.core.events`): ``attempts``
    made so far and their ``log`` (``[{attempt, at, status, error}]``); ``outcome`` is ``pending`` until it is
    ``delivered`` or ``abandoned`` (the attempts ran out); ``next_at``: when a pending one is next due (also the
    lease of the API process sending it)."""

    __tablename__ = "webhook_deliveries"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    event_seq: Mapped[int] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(16))
    outcome: Mapped[str] = mapped_column(String(16), index=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_at: Mapped[float] = mapped_column(Float)
    log: Mapped[list] = mapped_column(JSON, default=list)
    created_at: Mapped[float] = mapped_column(Float)


OUTPUT_KINDS = ("video", "mesh", "pointcloud")


class OutputRow(LeaseColumns, Base):
    """An output job: a video, mesh or point cloud made from a trained job's model by an ``outputs`` worker.

    The file lives in ``<data_dir>/runs/<job_id>/outputs/<id>/<file_name>`` (and in the object store under
    ``outputs/<id>`` when there is one). ``done``/``total`` count frames (video) or views (exports);
    ``attempt`` fences the claiming worker's writes as for training jobs (:class:`JobRow`). ``partial``: the
    trained job was cancelled, so its checkpoint is an unfinished model.
    """

    __tablename__ = "outputs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    state: Mapped[str] = mapped_column(String(16), index=True)
    params: Mapped[dict] = mapped_column(JSON)
    partial: Mapped[bool] = mapped_column(Boolean, default=False)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int | None] = mapped_column(Integer, nullable=True)
    eta_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    summary: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    file_name: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[float] = mapped_column(Float)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)


class ImportRow(LeaseColumns, Base):
    """A capture import: a raw capture (a ROS bag...) that a worker turns into a scene, which exists only once the
    import has succeeded (``scene_id``).

    The raw capture lives in ``<data_dir>/imports/<id>`` until the import ends. ``layout``: the importer
    (:data:`voxnerf.data.importers.QUEUED_LAYOUTS`); ``params``: the upload's choices (``splits``); ``stage``
    and ``progress``: where the importer is; ``step``: what the importer is doing within its stage ("matching
    features (sequential): 120 of 450 image pairs"), for the importers that say it; ``summary``: the importer's
    summary once succeeded. ``attempt`` fences the claiming worker's writes as for training jobs
    (:class:`JobRow`).
    """

    __tablename__ = "imports"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(255))
    layout: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), index=True)
    stage: Mapped[str | None] = mapped_column(String(64), nullable=True)
    step: Mapped[str | None] = mapped_column(String(255), nullable=True)
    params: Mapped[dict] = mapped_column(JSON)
    size_bytes: Mapped[int] = mapped_column(Integer)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    eta_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    scene_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    summary: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[float] = mapped_column(Float)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)


TOKEN_SCOPES = ("read", "write", "admin")


class TokenRow(Base):
    """A named API token (:mod:`app.core.tokens`). Only the SHA-256 of the token is kept; ``webhook_secret`` signs
    the webhooks of the work made with it; ``max_queued`` replaces the service's per-token queue limit when set.
    A revoked token keeps its row (its name stays recorded on the work it made and is never given again)."""

    __tablename__ = "tokens"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    scope: Mapped[str] = mapped_column(String(8))
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    webhook_secret: Mapped[str] = mapped_column(String(64))
    max_queued: Mapped[int | None] = mapped_column(Integer, nullable=True)
    created_at: Mapped[float] = mapped_column(Float)
    revoked_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    last_used_at: Mapped[float | None] = mapped_column(Float, nullable=True)
