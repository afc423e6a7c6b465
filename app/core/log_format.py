"""How the API and the workers write their logs: ``VOXNERF_LOG_FORMAT=text`` (lines for people, the default) or
``json`` (one JSON object per line, for log shippers: ``time``, ``level``, ``logger``, ``message``, the ids of the
work the line is about when known, ``exception`` with its traceback). Python's warnings are logged too.

The ids are a record's ``job_id`` / ``output_id`` / ``import_id`` attributes (``log.info(..., extra={...})``) or
those of the task the worker is running (:func:`work_ids`, which the workers set around each task). Masking is
the record factory's (:func:`app.core.redact.install_log_masking`): what reaches a formatter is already masked;
a traceback is masked again here, as formatters write it themselves.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator
from contextvars import ContextVar
from datetime import datetime, timezone

from app.core.redact import mask_url

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
WORK_ID_KEYS = ("job_id", "output_id", "import_id")
# the loggers that have handlers of their own besides the root's (uvicorn's, and Celery's task logger)
OWN_HANDLER_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access", "celery.task")
_work_ids: ContextVar[dict[str, str]] = ContextVar("voxnerf_work_ids", default={})  # noqa: B039 (never mutated)


@contextlib.contextmanager
def work_ids(**ids: str) -> Iterator[None]:
    """Within the block, every JSON log line names ``ids`` (``job_id=...``) unless its record names its own."""
    token = _work_ids.set({key: value for key, value in ids.items() if value})
    try:
        yield
    finally:
        _work_ids.reset(token)


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (newlines in the message or traceback escaped by JSON)."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": datetime.fromtimestamp(record.created, tz=timezone.utc).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        entry.update(_work_ids.get())
        entry.update({key: str(getattr(record, key)) for key in WORK_ID_KEYS if getattr(record, key, None)})
        if record.exc_info and record.exc_info[0] is not None:
            entry["exception"] = mask_url(record.exc_text or self.formatException(record.exc_info))
        elif record.exc_text:
            entry["exception"] = mask_url(record.exc_text)
        return json.dumps(entry, default=str, ensure_ascii=False)


def json_handlers(logger: logging.Logger) -> None:
    """Give every handler of ``logger`` the JSON formatter."""
    formatter = JsonFormatter()
    for handler in logger.handlers:
        handler.setFormatter(formatter)


def configure_logging(log_format: str, level: int = logging.INFO) -> None:
    """Logging of a process that starts the service or a worker: the root logger at ``level`` writes to stderr in
    ``log_format`` (``text``: :data:`TEXT_FORMAT`; ``json``: :class:`JsonFormatter`, and so do the handlers
    uvicorn and Celery attached to their own loggers, :data:`OWN_HANDLER_LOGGERS`). Idempotent."""
    root = logging.getLogger()
    if log_format != "json":
        logging.basicConfig(level=level, format=TEXT_FORMAT)
        return
    if not root.handlers:
        root.addHandler(logging.StreamHandler())
    if root.level == logging.NOTSET or root.level > level:
        root.setLevel(level)
    logging.captureWarnings(True)  # Python's warnings become records of logger py.warnings, not bare stderr text
    for logger in (root, *map(logging.getLogger, OWN_HANDLER_LOGGERS)):
        json_handlers(logger)
