"""A worker's JSON logs (``VOXNERF_LOG_FORMAT=json``, :mod:`app.core.log_format`): the handlers Celery attaches
while it starts get the JSON formatter too, and every line written while a task runs names the work it is about
(a training job's ``job_id``, an output's ``output_id``, an import's ``import_id``; a render's ``job_id``)."""

from __future__ import annotations

import contextlib
from typing import Any

from celery.signals import after_setup_logger, after_setup_task_logger, task_postrun, task_prerun

from app.core.celery_app import IMPORT_TASK, OUTPUT_TASK, RENDER_TASK, TRAIN_TASK
from app.core.log_format import json_handlers, work_ids

# task name -> (the id's key in a log line, the position of that id among the task's arguments)
TASK_WORK_IDS = {TRAIN_TASK: ("job_id", 0), OUTPUT_TASK: ("output_id", 0), IMPORT_TASK: ("import_id", 0),
                 RENDER_TASK: ("job_id", 1)}
_open: dict[str, contextlib.ExitStack] = {}  # task id -> the work_ids block of the task running in this process


def _json_logger(logger: Any = None, **_kwargs: Any) -> None:
    json_handlers(logger)


def _enter_task(task_id: str | None = None, task: Any = None, args: Any = None, **_kwargs: Any) -> None:
    key, position = TASK_WORK_IDS.get(getattr(task, "name", ""), (None, 0))
    if key is None or task_id is None or not args or len(args) <= position:
        return
    stack = contextlib.ExitStack()
    stack.enter_context(work_ids(**{key: str(args[position])}))
    _open[task_id] = stack


def _leave_task(task_id: str | None = None, **_kwargs: Any) -> None:
    stack = _open.pop(task_id, None) if task_id is not None else None
    if stack is not None:
        stack.close()


def install() -> None:
    """Connect the receivers (before the worker starts)."""
    after_setup_logger.connect(_json_logger, weak=False)
    after_setup_task_logger.connect(_json_logger, weak=False)
    task_prerun.connect(_enter_task, weak=False)
    task_postrun.connect(_leave_task, weak=False)
