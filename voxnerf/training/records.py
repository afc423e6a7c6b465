"""What travels out of training: stage records, evaluation records, progress events and the report.

These pydantic models are the contract between the engine and its callers: ``train()`` returns a
:class:`TrainReport` (written to ``report.json`` by :meth:`TrainReport.to_json_dict`), ``on_progress`` receives
:class:`ProgressEvent` objects, and the service's job store and REST schemas derive their fields from them.
This module imports no torch, so the API process can use it.

Units: seconds are wall-clock seconds; ``elapsed_s`` / ``train_seconds`` are training seconds (evaluation
time excluded), ``wall_s`` / ``wall_seconds`` the command's wall clock; PSNR in dB.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

RunStatus = Literal["running", "succeeded", "cancelled", "diverged"]
EventStage = str  # a set-up stage's name (StageRecord.name), "train", "final_eval" or "done"


class StageRecord(BaseModel):
    """One stage of a run: whether it ran, why (or why not), and its seconds."""

    model_config = ConfigDict(extra="forbid")

    name: str
    ran: bool
    why: str
    seconds: float = 0.0


class EvalRecord(BaseModel):
    """One evaluation during or after training: PSNR (dB) per split against training seconds.

    ``full`` marks an ``--eval-at`` evaluation of every view (with ``ssim`` and ``progress_psnr``), ``final``
    the final evaluation. ``progress_psnr`` is the mean PSNR over the views a progress evaluation uses, so one
    curve runs through progress and full evaluations alike. Keys that were never set stay out of the JSON.
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
    progress_psnr: dict[str, float | None] | None = None

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


class TrainReport(BaseModel):
    """A run's report: ``run_dir/report.json`` and what ``train()`` returns.

    ``scene``, ``prior`` and ``octree`` are the summaries of those stages' objects; ``warnings`` lists what the
    user should know (a prior that few pixels see, a sampler asking for a prior the scene lacks). Fields that a
    run never set (a prior-less scene has no ``prior``) stay out of the JSON.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=False)

    # Field order is report.json's key order (that of the keys as a run sets them).
    status: RunStatus = "running"
    config: dict[str, Any]
    device: str
    stages: list[StageRecord] = []
    history: list[EvalRecord] = []
    scene: dict[str, Any] | None = None
    prior: dict[str, Any] | None = None
    resumed_from_iteration: int | None = None
    octree: dict[str, Any] | None = None
    warnings: list[str] = []
    depth_beta: float | None = None
    depth: dict[str, Any] | None = None
    metrics: dict[str, Any] | None = None
    error: str | None = None
    iteration: int = 0
    train_seconds: float | None = None
    wall_seconds: float | None = None
    throughput: dict[str, int | float] | None = None
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
