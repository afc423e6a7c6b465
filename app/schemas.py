"""Request and response bodies of the REST API (pydantic). Field names are the public contract."""

from __future__ import annotations

import math
from datetime import datetime, timezone
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.jobstore import ID_RE
from voxnerf.cameras import Intrinsics
from voxnerf.config import Preset, SamplerName
from voxnerf.scene import ROTATION_TOLERANCE

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
OutputName = Literal["rgb", "depth", "opacity"]
MEDIA_TYPES = {"png": "image/png", "exr": "image/x-exr"}


def _utc(seconds: float | None) -> datetime | None:
    return None if seconds is None else datetime.fromtimestamp(seconds, tz=timezone.utc)


# ------------------------------------------------------------------------------------------------ scenes


class PriorSummary(BaseModel):
    model_config = ConfigDict(extra="allow")

    file: str
    kind: str | None = None
    sigma: float | None = Field(None, description="standard deviation of the prior's noise, scene units")
    sigma_estimated: bool | None = None


class SceneSummary(BaseModel):
    """What :func:`voxnerf.scene.inspect_scene` found in the upload."""

    model_config = ConfigDict(extra="allow")

    frames: int
    splits: dict[str, int] = Field(description="frames per split (train, test, named evaluation splits)")
    image_size: list[int] = Field(description="[width, height] of the first training image, pixels")
    prior: PriorSummary | None
    depth: bool = Field(description="whether frames carry sensor depth maps")
    warnings: list[str] = []


class SceneOut(BaseModel):
    id: str
    name: str
    created_at: datetime
    size_bytes: int
    summary: SceneSummary

    @classmethod
    def from_row(cls, row) -> SceneOut:
        return cls(
            id=row.id,
            name=row.name,
            created_at=_utc(row.created_at),
            size_bytes=row.size_bytes,
            summary=SceneSummary.model_validate(row.summary),
        )


# ------------------------------------------------------------------------------------------------ jobs


class JobOptions(BaseModel):
    """Training options, named as the CLI's ``voxnerf train`` flags. At least one bound is required."""

    model_config = ConfigDict(extra="forbid")

    preset: Preset = "cpu"
    sampler: SamplerName = "voxnerf"
    max_seconds: float | None = Field(None, gt=0, le=7 * 24 * 3600, description="wall-clock bound, seconds")
    max_iters: int | None = Field(None, gt=0, le=10_000_000)
    depth_loss: bool = True
    downscale: int = Field(1, ge=1, le=16)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    compile: bool = Field(True, description="torch.compile the training step")
    hash_kernel: bool = Field(True, description="on a CPU worker, the hash encoding's C kernel where it builds")
    eval_at: list[float] = Field([], max_length=64, description="full evaluations at these training seconds")
    eval_every_s: float | None = Field(
        None, gt=0, description="training seconds between PSNR evaluations (the history); engine default 30"
    )

    @model_validator(mode="after")
    def _bounded(self) -> JobOptions:
        if self.max_seconds is None and self.max_iters is None:
            raise ValueError("give max_seconds or max_iters (or both)")
        if any(not (math.isfinite(t) and t > 0) for t in self.eval_at):
            raise ValueError("eval_at: seconds must be positive finite numbers")
        return self


class HistoryPoint(BaseModel):
    """One evaluation during training: PSNR (dB) per split against training seconds."""

    model_config = ConfigDict(extra="allow")

    elapsed_s: float = Field(description="training seconds (evaluation time excluded)")
    wall_s: float | None = None
    iteration: int
    loss: float | None = None
    psnr: dict[str, float | None] = {}
    final: bool = False


class StageInfo(BaseModel):
    model_config = ConfigDict(extra="allow")

    name: str
    ran: bool
    why: str
    seconds: float | None = None


class JobOut(BaseModel):
    id: str
    scene_id: str
    state: JobState
    progress: float = Field(description="0..1")
    eta_s: float | None = Field(description="estimated seconds left while running")
    stage: str | None
    iteration: int
    elapsed_s: float = Field(description="training seconds so far")
    loss: float | None
    history: list[HistoryPoint]
    stages: list[StageInfo] = Field(description="pipeline stages, whether each ran and why")
    metrics: dict | None = Field(description="report metrics per evaluation split, when succeeded")
    error: str | None
    cancel_requested: bool
    options: dict
    attempt: int = Field(description="how many times a worker has claimed the job")
    requeues: int = Field(description="how many times the job was requeued after its worker died")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None

    @classmethod
    def from_row(cls, row) -> JobOut:
        return cls(
            id=row.id,
            scene_id=row.scene_id,
            state=row.state,
            progress=row.progress,
            eta_s=row.eta_s,
            stage=row.stage,
            iteration=row.iteration,
            elapsed_s=row.elapsed_s,
            loss=row.loss,
            history=row.history or [],
            stages=row.stages or [],
            metrics=row.metrics,
            error=row.error,
            cancel_requested=row.cancel_requested,
            options=row.options,
            attempt=row.attempt,
            requeues=row.requeues,
            created_at=_utc(row.created_at),
            started_at=_utc(row.started_at),
            finished_at=_utc(row.finished_at),
        )


class EvalRender(BaseModel):
    split: str
    name: str
    url: str


# ------------------------------------------------------------------------------------------------ render


class RenderRequest(BaseModel):
    """One view of a finished job. Missing intrinsics come from the scene's first training camera.

    ``width``/``height`` come together; when given, every missing intrinsic is the default scaled by
    ``width / default width`` (x) and ``height / default height`` (y). PNG holds one output: ``rgb`` (8-bit
    sRGB-encoded colour), ``depth`` (16-bit, in the scene's ``depth_unit_scale_factor`` units) or ``opacity``
    (8-bit gray). EXR holds any of them as float32 channels R, G, B, Z (depth, scene units) and A (opacity).
    Default outputs: ``["rgb"]`` for PNG, all three for EXR.
    """

    model_config = ConfigDict(extra="forbid")

    job_id: str = Field(pattern=ID_RE.pattern, description="a succeeded job's id")
    transform_matrix: list[list[float]] = Field(
        description="4x4 camera-to-world, OpenGL axes (camera looks along -Z, +Y up), scene units"
    )
    width: int | None = Field(None, ge=1, le=16384)
    height: int | None = Field(None, ge=1, le=16384)
    fl_x: float | None = Field(None, gt=0)
    fl_y: float | None = Field(None, gt=0)
    cx: float | None = None
    cy: float | None = None
    format: Literal["png", "exr"] = "png"
    outputs: list[OutputName] | None = None

    @field_validator("fl_x", "fl_y", "cx", "cy")
    @classmethod
    def _finite(cls, value: float | None) -> float | None:
        if value is not None and not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @field_validator("transform_matrix")
    @classmethod
    def _pose(cls, value: list[list[float]]) -> list[list[float]]:
        mat = np.asarray(value, dtype=np.float64) if all(len(r) == 4 for r in value) else None
        if mat is None or mat.shape != (4, 4):
            raise ValueError("must be a 4x4 matrix (a list of 4 rows of 4 numbers)")
        if not np.isfinite(mat).all():
            raise ValueError("contains NaN or inf")
        if not np.allclose(mat[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError(f"last row must be [0, 0, 0, 1], got {mat[3].tolist()}")
        rot = mat[:3, :3]
        deviation = float(np.abs(rot.T @ rot - np.eye(3)).max())
        det = float(np.linalg.det(rot))
        if deviation > ROTATION_TOLERANCE or det <= 0:
            raise ValueError(
                f"rotation is not a proper orthonormal matrix (max |R^T R - I| = {deviation:.3g}, "
                f"det = {det:.3g})"
            )
        if deviation > 1e-9:
            u, _, vt = np.linalg.svd(rot)
            mat[:3, :3] = u @ vt
        return mat.tolist()

    @model_validator(mode="after")
    def _consistent(self) -> RenderRequest:
        if (self.width is None) != (self.height is None):
            raise ValueError("give width and height together (or neither, for the scene's size)")
        if self.outputs is None:
            self.outputs = ["rgb"] if self.format == "png" else ["rgb", "depth", "opacity"]
        self.outputs = list(dict.fromkeys(self.outputs))
        if not self.outputs:
            raise ValueError("outputs must name at least one of rgb, depth, opacity")
        if self.format == "png" and len(self.outputs) != 1:
            raise ValueError("a PNG holds one output: ask for one of rgb, depth, opacity, or use format exr")
        return self

    @property
    def media_type(self) -> str:
        return MEDIA_TYPES[self.format]

    def pixels(self) -> int | None:
        """width x height when given (the default size is the scene's own)."""
        return None if self.width is None else self.width * int(self.height)

    def intrinsics(self, default: Intrinsics) -> Intrinsics:
        """The camera to render, filling what the request leaves out from ``default`` (see class doc)."""
        width = self.width or default.width
        height = self.height or default.height
        sx, sy = width / default.width, height / default.height
        return Intrinsics(
            fl_x=self.fl_x if self.fl_x is not None else default.fl_x * sx,
            fl_y=self.fl_y if self.fl_y is not None else default.fl_y * sy,
            cx=self.cx if self.cx is not None else default.cx * sx,
            cy=self.cy if self.cy is not None else default.cy * sy,
            width=width,
            height=height,
        )


# ------------------------------------------------------------------------------------------------ health


class Check(BaseModel):
    ok: bool
    detail: str


class HealthOut(BaseModel):
    status: Literal["ok", "unavailable"]
    database: Check
    broker: Check
    workers: dict[str, list[str]] = Field(description="queue name -> names of live workers consuming it")
