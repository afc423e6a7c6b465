"""``/jobs``: list, show, cancel, delete; the evaluation renders, report.json and checkpoint of a job's run."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from urllib.parse import quote

from fastapi import APIRouter, HTTPException, Query, Response
from fastapi.responses import FileResponse

from app.api_reference import EXAMPLE_ID, error_responses
from app.core import jobstore, outputs, storage
from app.core.jobstore import JOBS
from app.core.models import JobRow
from app.core.redact import public_error
from app.core.settings import Settings
from app.deps import JobId, PrincipalDep, SettingsDep, require_owner
from app.routes import work
from app.schemas import EvalRender, JobOut
from voxnerf.files import CHECKPOINT, REPORT

log = logging.getLogger(__name__)
router = APIRouter(tags=["jobs"])

EVAL_DIR = "eval"  # the trainer writes <run_dir>/eval/<split>/<view name>.png
NAME_MAX_BYTES = 255


def _job_or_404(settings: Settings, job_id: str) -> JobRow:
    return work.found(settings, JOBS, job_id)


@router.get("/jobs", response_model=list[JobOut], summary="List jobs, newest first")
def list_jobs(
    settings: SettingsDep,
    limit: int = Query(100, ge=1, le=1000),
    scene_id: str | None = Query(None, pattern=jobstore.ID_RE.pattern),
) -> list[JobOut]:
    """Training jobs with their state and progress, newest first; ``scene_id`` keeps those of one scene."""
    return [JobOut.from_row(row) for row in JOBS.newest(settings, limit, scene_id=scene_id)]


@router.get("/jobs/{job_id}", response_model=JobOut, summary="State, progress, ETA, history, stages, metrics",
            responses=error_responses(404))
def get_job(job_id: JobId, settings: SettingsDep) -> JobOut:
    """The job as it is now: state, options, progress (stage, iteration, ETA), PSNR history, stage records, and
    once it has succeeded its metrics per evaluation split."""
    return JobOut.from_row(_job_or_404(settings, job_id))


@router.post("/jobs/{job_id}/cancel", status_code=202, response_model=JobOut, summary="Cancel a job",
             responses=error_responses(404, 409, e409=f"job {EXAMPLE_ID} already succeeded"))
def cancel_job(job_id: JobId, settings: SettingsDep, principal: PrincipalDep) -> JobOut:
    """Cancel a queued job at once, a running one at its next iteration (its checkpoint is kept); 403 for another
    token's job (scope write)."""
    return JobOut.from_row(work.cancel(settings, JOBS, job_id, principal))


@router.delete("/jobs/{job_id}", status_code=204, summary="Delete a finished job, its run and its outputs",
               responses=error_responses(404, 409, e409=f"job {EXAMPLE_ID} is running; cancel it and wait for it "
                                         "to stop first"))
def delete_job(job_id: JobId, settings: SettingsDep, principal: PrincipalDep) -> Response:
    """Delete a succeeded, failed or cancelled job: its row, its output jobs, its run directory (checkpoint,
    report, renders, outputs) here and in the object store. 409 while it or one of its outputs is queued or
    running (cancel it first), 404 for an unknown job, 403 for another token's job (scope write)."""
    require_owner(principal, f"job {job_id}", _job_or_404(settings, job_id).created_by)
    try:
        output_ids = jobstore.delete_job(settings, job_id)
    except jobstore.JobActive as busy:
        raise HTTPException(409, str(busy)) from None
    if output_ids is None:
        raise HTTPException(404, f"no job {job_id}")
    log.info("job %s and its %d output(s) deleted by %r", job_id, len(output_ids), principal.name)
    shutil.rmtree(settings.runs_dir / job_id, ignore_errors=True)
    try:
        storage.delete_keys(settings, [f"{storage.RUNS}/{job_id}", *map(outputs.store_key, output_ids)])
    except Exception:  # the job is gone for the service; its unreferenced copy in the store is only waste
        log.error("job %s: deleting its run in the object store failed", job_id, exc_info=True)
    return Response(status_code=204)


def _run_dir(settings: Settings, job: JobRow) -> Path:
    """Job ``job``'s run directory; a succeeded job's run is fetched from the store first when this process's
    cache lacks it (a no-op without ``storage_url``)."""
    if job.state != "succeeded":
        return settings.runs_dir / job.id
    try:
        return storage.ensure_run(settings, job.id, refresh=False)
    except storage.StorageError as err:
        detail = public_error(f"the run of job {job.id} cannot be fetched from the store: {err}", settings)
        raise HTTPException(503, detail) from None


def _eval_root(settings: Settings, job: JobRow) -> Path:
    """Where job ``job``'s evaluation renders are (:func:`_run_dir`)."""
    return _run_dir(settings, job) / EVAL_DIR


@router.get("/jobs/{job_id}/renders", response_model=list[EvalRender], summary="Evaluation renders of a job",
            responses=error_responses(404, 503))
def list_renders(job_id: JobId, settings: SettingsDep) -> list[EvalRender]:
    """The evaluation renders the run has written so far (split, view name, URL to download the PNG)."""
    root = _eval_root(settings, _job_or_404(settings, job_id))
    if not root.is_dir():
        return []
    return [
        EvalRender(
            split=path.parent.name,
            name=path.stem,
            url=f"/jobs/{job_id}/renders/{quote(path.parent.name, safe='')}/{quote(path.name, safe='')}",
        )
        for path in sorted(root.glob("*/*.png"))
        if path.is_file() and not path.name.startswith(".")
    ]


def _plain_name(value: str) -> bool:
    """One file name: not empty, no dot entry, no separator or NUL, at most 255 bytes (the usual NAME_MAX,
    so an overlong segment is a 404 rather than an ENAMETOOLONG from the filesystem)."""
    return (
        bool(value)
        and len(value.encode()) <= NAME_MAX_BYTES
        and value not in (".", "..")
        and not any(c in value for c in "/\\\x00")
    )


@router.get(
    "/jobs/{job_id}/renders/{split}/{filename}",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}}, **error_responses(404, 503, e404="no such render")},
    summary="Download one evaluation render (PNG)",
)
def get_render(job_id: JobId, split: str, filename: str, settings: SettingsDep) -> FileResponse:
    """One PNG of ``GET /jobs/{id}/renders``: ``split`` and ``filename`` as that list's URL names them."""
    job = _job_or_404(settings, job_id)
    if not (_plain_name(split) and _plain_name(filename) and filename.endswith(".png")):
        raise HTTPException(404, "no such render")
    root = _eval_root(settings, job).resolve()
    path = (root / split / filename).resolve()
    if not path.is_relative_to(root) or not path.is_file():
        raise HTTPException(404, "no such render")
    return FileResponse(path, media_type="image/png")


@router.get(
    "/jobs/{job_id}/report",
    response_class=FileResponse,
    responses={200: {"content": {"application/json": {}}},
               **error_responses(404, 503, e404=f"job {EXAMPLE_ID} has no report.json (running): a run writes it "
                                 "when it ends")},
    summary="Download the run's report.json (config, stages, history, metrics); written when the run ends",
)
def get_report(job_id: JobId, settings: SettingsDep) -> FileResponse:
    """The run's report.json as ``voxnerf train`` writes it: the configuration, stage records, PSNR history and
    final metrics; 404 until the run has ended."""
    job = _job_or_404(settings, job_id)
    path = _run_dir(settings, job) / REPORT
    if not path.is_file():
        raise HTTPException(404, f"job {job_id} has no report.json ({job.state}): a run writes it when it ends")
    return FileResponse(path, media_type="application/json", filename=f"report-{job_id}.json")


@router.get(
    "/jobs/{job_id}/checkpoint",
    response_class=FileResponse,
    responses={200: {"content": {"application/octet-stream": {}}}, **error_responses(404, 409, 503)},
    summary="Download the run's checkpoint (checkpoint.pt: `voxnerf render` reads it from a run directory)",
)
def get_checkpoint(job_id: JobId, settings: SettingsDep) -> FileResponse:
    """The last checkpoint of a finished job (succeeded, cancelled, or failed after training started); 409 while
    the job is queued or running (the file is being replaced), 404 when no checkpoint was written."""
    job = _job_or_404(settings, job_id)
    if job.state in ("queued", "running"):
        raise HTTPException(409, f"job {job_id} is {job.state}: its checkpoint is still being written")
    path = _run_dir(settings, job) / CHECKPOINT
    if not path.is_file():
        raise HTTPException(404, f"job {job_id} has no checkpoint ({job.state} before training started)")
    return FileResponse(path, media_type="application/octet-stream", filename=f"checkpoint-{job_id}.pt")
