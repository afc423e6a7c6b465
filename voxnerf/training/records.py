"""What travels out of training: stage records, evaluation records, progress events and the report.

These pydantic models are the contract between the engine and its callers: ``train()`` returns a
:class:`TrainReport` (written to ``report.json`` by :meth:`TrainReport.to_json_dict`), ``on_progress`` receives
:class:`ProgressEvent` objects, and the service's job store and REST schemas derive their fields from them.
This module imports no torch, so the API process can use it.

Units: seconds are wall-clock seconds; ``elapsed_s`` / ``train_seconds`` are training seconds (the training
loop's, its evaluations, checkpoints and compilation excluded), ``wall_s`` / ``wall_seconds`` the command's wall
clock; PSNR in dB. ``loss_series`` is the training loss against training seconds, bounded by :class:`LossSeries`.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

RunStatus = Literal["running", "succeeded", "cancelled", "diverged"]
EventStage = str  # a set-up stage's name (StageRecord.name), "train", "final_eval" or "done"
LossPoint = tuple[float, float]  # (training seconds, mean training loss of the steps the point covers)
LOSS_SERIES_MAX_POINTS = 300


class StageRecord(BaseModel):
    """One stage of a run: whether it ran, why (or why not), and its seconds."""

    model_config = ConfigDict(extra="forbid")

    name: str
    ran: bool
    why: str
    seconds: float = 0.0


class EvalRecord(BaseModel):
    """One evaluation during or after training: PSNR (dB) per split against training seconds.

    A progress evaluation scores ``rays`` pixels spread over a few views per split (a subsample of their pixels
    where the whole views would cost more than the progress evaluations' share of the budget). ``full`` marks an
    ``--eval-at`` evaluation of every view (with ``ssim``, ``lpips``, ``half`` (the half-image
    protocol's means per split) and ``progress_psnr``), ``final`` the final evaluation. ``progress_psnr`` is the
    mean PSNR over the views a progress evaluation uses, so one curve runs through progress and full evaluations
    alike. Keys that were never set stay out of the JSON.
    """

    model_config = ConfigDict(extra="forbid")

    elapsed_s: float = Field(description="training seconds (evaluation time excluded)")
    wall_s: float | None = None
    iteration: int
    loss: float | None = None
    psnr: dict[str, float | None] = {}
    full: bool = False
    final: bool = False
    ssim: dict[str, float | None] | None = None
    lpips: dict[str, float | None] | None = None
    half: dict[str, dict[str, float | None]] | None = None
    progress_psnr: dict[str, float | None] | None = None
    rays: int | None = Field(None, description="a progress evaluation's rays (pixels) scored, over all its views")

    def to_json_dict(self) -> dict[str, Any]:
        return self.model_dump(exclude_unset=True)


class ProgressEvent(BaseModel):
    """What ``on_progress`` receives: at each stage, about once a second while training, and at the end."""

    model_config = ConfigDict(extra="forbid")

    stage: EventStage = Field(description="the stage running: a set-up stage's name, train, final_eval or done")
    iteration: int = Field(0, description="training iterations so far")
    max_iters: int | None = Field(None, description="the iteration bound, when the run has one")
    elapsed_s: float = Field(0.0, description="training seconds so far (evaluation time excluded)")
    progress: float = Field(0.0, ge=0.0, le=1.0, description="0..1, the larger of the iteration and time fractions")
    eta_s: float | None = Field(None, description="estimated seconds left while running")
    loss: float | None = Field(None, description="the last training loss (None until the first finite one)")
    history: list[EvalRecord] = Field([], description="the evaluations so far: PSNR per split against seconds")
    stages: list[StageRecord] = Field([], description="pipeline stages so far, whether each ran and why")
    loss_series: list[LossPoint] = Field(
        [], description=f"the training loss against training seconds: [seconds, mean loss of the steps since the "
        f"previous point] pairs, evenly thinned to at most {LOSS_SERIES_MAX_POINTS} points")
    checkpoint_iteration: int | None = Field(
        None, description="the iteration of the run's last complete checkpoint, which renders of an unfinished run "
        "use; None before the first")


class LossSeries:
    """The training loss against training seconds, bounded: at most ``max_points`` points, evenly spaced.

    :meth:`add` takes every step's loss (non-finite ones are left out); :meth:`close` ends a point at the given
    training seconds, holding the mean loss of the steps added since the previous point, once ``gap`` seconds
    have passed since it. When the series outgrows ``max_points`` its points are merged in pairs
    (:func:`merge_pairs`) and the gap doubles, so the points always cover the whole run at one spacing.
    """

    def __init__(self, max_points: int = LOSS_SERIES_MAX_POINTS, gap: float = 1.0) -> None:
        if max_points < 3:
            raise ValueError(f"max_points must be at least 3, got {max_points}")
        self.max_points, self.gap = max_points, gap
        self.points: list[LossPoint] = []
        self._sum, self._count = 0.0, 0

    def add(self, loss: float) -> None:
        if math.isfinite(loss):
            self._sum += loss
            self._count += 1

    def close(self, seconds: float) -> bool:
        """End a point at ``seconds`` when steps were added and ``gap`` has passed; whether one was added."""
        if not self._count or (self.points and seconds - self.points[-1][0] < self.gap):
            return False
        self.points.append((round(seconds, 2), float(f"{self._sum / self._count:.5g}")))
        self._sum, self._count = 0.0, 0
        if len(self.points) > self.max_points:
            self.points = merge_pairs(self.points)
            self.gap *= 2
        return True


def merge_pairs(points: list[LossPoint]) -> list[LossPoint]:
    """About half as many points: the first kept as it is (a series' start never moves, so a job store can
    tell a resumed run's series from the points before it), each following pair merged into one at the later
    one's seconds holding the pair's mean loss, and an odd last point kept as it is."""
    rest = points[1:]
    merged = [(b[0], float(f"{(a[1] + b[1]) / 2:.5g}")) for a, b in zip(rest[0::2], rest[1::2], strict=False)]
    return points[:1] + merged + ([rest[-1]] if len(rest) % 2 else [])


def thin_series(points: list[LossPoint], max_points: int = LOSS_SERIES_MAX_POINTS) -> list[LossPoint]:
    """``points`` merged in pairs (:func:`merge_pairs`) until at most ``max_points`` are left."""
    while len(points) > max_points:
        points = merge_pairs(points)
    return points


class TrainReport(BaseModel):
    """A run's report: ``run_dir/report.json`` and what ``train()`` returns.

    ``scene``, ``prior`` and ``octree`` are the summaries of those stages' objects; ``warnings`` lists what the
    user should know (a prior that few pixels see, a sampler asking for a prior the scene lacks); ``pose_refinement``
    and ``appearance`` the size of the learnt per-image corrections (configs of those names); ``window_check`` how
    well the VoxNeRF sampler's window holds the depth maps' surface (:mod:`voxnerf.training.window_check`, measured
    at set-up); ``budget`` what ``max_seconds`` charged, the share of it that trained and the command's seconds by
    part (:meth:`voxnerf.training.budget.Budget.accounting`); ``runtime`` how the process that trained computed
    (:func:`voxnerf.devices.compute_environment`), with ``octree_misses``: how the voxnerf sampler gave the rays
    that miss its octree their samples (:data:`voxnerf.model.samplers.OCTREE_MISSES`; None without that sampler).
    Fields that a run never set (a prior-less scene has no ``prior``) stay out of the JSON.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=False)

    # Field order is report.json's key order (that of the keys as a run sets them).
    status: RunStatus = "running"
    config: dict[str, Any]
    device: str
    stages: list[StageRecord] = []
    history: list[EvalRecord] = []
    loss_series: list[LossPoint] = []
    scene: dict[str, Any] | None = None
    prior: dict[str, Any] | None = None
    resumed_from_iteration: int | None = None
    octree: dict[str, Any] | None = None
    warnings: list[str] = []
    depth_beta: float | None = None
    depth: dict[str, Any] | None = None
    window_check: dict[str, Any] | None = None
    pose_refinement: dict[str, Any] | None = None
    appearance: dict[str, Any] | None = None
    metrics: dict[str, Any] | None = None
    error: str | None = None
    iteration: int = 0
    train_seconds: float | None = None
    wall_seconds: float | None = None
    throughput: dict[str, int | float] | None = None
    budget: dict[str, Any] | None = None
    runtime: dict[str, str | int | bool | None] | None = None
    checkpoint_kept: bool | None = None

    def to_json_dict(self) -> dict[str, Any]:
        """The report.json form: every field set during the run (always status, config, device, stages and
        history; warnings when there are any), with history entries keeping only their own keys."""
        data = self.model_dump(exclude={"history"})
        data["history"] = [h.to_json_dict() for h in self.history]
        keep = {"status", "config", "device", "stages", "history"} | (self.model_fields_set - {"warnings"})
        if self.warnings:
            keep.add("warnings")
        return {name: data[name] for name in type(self).model_fields if name in keep}

    @classmethod
    def from_json_dict(cls, data: dict[str, Any]) -> TrainReport:
        return cls.model_validate(data)
