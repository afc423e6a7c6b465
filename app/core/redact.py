"""What the service lets out in words: credentials masked in URLs, server paths cut down to relative ones.

- :func:`mask_url`: the password (or bare user token) of every ``scheme://user:password@host`` URL in a text,
  and the values of secret-looking query parameters (``?password=``, ``&secret_key=``...), become ``***``;
- :func:`install_log_masking`: every log record of the process (and of processes it forks) goes through
  :func:`mask_url`: message, arguments and traceback;
- :func:`public_error`: an error message as clients may read it (job and output ``error``, HTTP ``detail``):
  URLs masked, and paths under ``data_dir`` relative to it (``runs/<id>/checkpoint.pt``).
"""

from __future__ import annotations

import logging
import os
import re
from typing import Any

from app.core.settings import Settings

MASK = "***"
# scheme://userinfo@ : userinfo runs to the last '@' before the host's '/' (a password may hold an '@')
_USERINFO = re.compile(r"\b([a-zA-Z][a-zA-Z0-9+.\-]*://)([^/?#\s'\"<>]*)@")
_SECRET_QUERY = re.compile(
    r"([?&;][\w.\-]*(?:password|passwd|pwd|secret|token|signature|credential|access_key|key)[\w.\-]*=)[^&;\s'\"<>]*",
    re.IGNORECASE,
)


def mask_url(text: str | None) -> str | None:
    """``text`` (a URL, or any text holding URLs) with credentials replaced by ``***``: the password of
    ``user:password@`` (the user stays), a userinfo without ``:`` as a whole (it may be a token), and the
    values of query parameters whose names hold password, secret, token, key, signature or credential.
    None stays None."""
    if text is None:
        return None
    return _SECRET_QUERY.sub(rf"\g<1>{MASK}", _USERINFO.sub(_masked_userinfo, text))


def _masked_userinfo(match: re.Match) -> str:
    user, colon, _ = match.group(2).partition(":")
    return f"{match.group(1)}{user}:{MASK}@" if colon else f"{match.group(1)}{MASK}@"


def public_error(text: str, settings: Settings) -> str:
    """An error message fit for a client: :func:`mask_url`, then every path under ``settings.data_dir``
    written relative to it (``/srv/voxnerf/runs/a/checkpoint.pt`` -> ``runs/a/checkpoint.pt``) and the
    directory itself as ``<data_dir>``."""
    text = mask_url(text)
    for root in sorted({str(settings.data_dir), os.path.realpath(settings.data_dir)}, key=len, reverse=True):
        text = text.replace(root.rstrip("/") + "/", "")
        text = re.sub(re.escape(root) + r"(?![\w.\-])", "<data_dir>", text)
    return text


# ------------------------------------------------------------------------------------------------ logging


def _masked_arg(value: Any) -> Any:
    """A log argument with :func:`mask_url` applied: strings always, other objects (an exception, a Path)
    only when their text holds credentials (then as the masked text); numbers and None as they are."""
    if isinstance(value, str):
        return mask_url(value)
    if value is None or isinstance(value, (int, float)):
        return value
    try:
        text = str(value)
    except Exception:  # its formatting fails later, in the handler, which reports that on its own
        return value
    masked = mask_url(text)
    return value if masked == text else masked


def mask_record(record: logging.LogRecord) -> logging.LogRecord:
    """``record`` with :func:`mask_url` applied to its message, its arguments (same arity, so formatters that
    unpack them keep working) and, when it carries an exception whose text holds credentials, its
    traceback text (``exc_text``, which formatters use as it is)."""
    if isinstance(record.msg, str):
        record.msg = mask_url(record.msg)
    if isinstance(record.args, tuple):
        record.args = tuple(_masked_arg(a) for a in record.args)
    elif isinstance(record.args, dict):
        record.args = {k: _masked_arg(v) for k, v in record.args.items()}
    if record.exc_info and record.exc_info[0] is not None and not record.exc_text:
        text = logging.Formatter().formatException(record.exc_info)
        masked = mask_url(text)
        if masked != text:
            record.exc_text = masked
    return record


def install_log_masking() -> None:
    """From now on every log record this process creates (any logger, any handler: Celery's and uvicorn's
    included) goes through :func:`mask_record`. A record factory, not a handler filter, so it survives
    handlers being replaced (Celery's worker does so) and is inherited by forked pool processes.
    Idempotent."""
    current = logging.getLogRecordFactory()
    if getattr(current, "masks_credentials", False):
        return

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        return mask_record(current(*args, **kwargs))

    factory.masks_credentials = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(factory)
