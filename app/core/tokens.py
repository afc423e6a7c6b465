"""The webhook signing secret of a principal (who made a job): the key of its deliveries' HMAC signatures.

Only the principals that exist without named tokens are known here: ``admin`` (the holder of ``VOXNERF_API_TOKEN``,
whose secret is derived from the token, so it changes when the token does) and ``local`` (a tokenless service's
loopback clients, whose secret is 32 random bytes in ``<data_dir>/webhook_secret``, made once, readable by its owner
only). Named tokens, each with a secret of its own, extend :func:`webhook_secret`.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import secrets
import tempfile

from app.core.settings import Settings
from voxnerf.errors import VoxNeRFError

LEGACY_ADMIN = "admin"  # the principal of VOXNERF_API_TOKEN
LOCAL = "local"  # the principal of every request to a tokenless service
LEGACY_WEBHOOK_MESSAGE = b"voxnerf-webhook"
LOCAL_WEBHOOK_SECRET_FILE = "webhook_secret"
SECRET_BYTES = 32


class TokenError(VoxNeRFError):
    """No webhook secret exists for a principal, or its secret file is damaged; ``status``: the HTTP status."""

    def __init__(self, message: str, status: int = 422) -> None:
        super().__init__(message)
        self.status = status


def _local_webhook_secret(settings: Settings) -> bytes:
    """``<data_dir>/webhook_secret``'s 32 bytes, made once: written whole to a private temporary file (0600) that is
    then hard-linked into place, which fails when the file exists, so processes starting together agree on one and
    none reads a half-written secret."""
    path = settings.data_dir / LOCAL_WEBHOOK_SECRET_FILE
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        fd, temporary = tempfile.mkstemp(prefix=".webhook_secret-", dir=settings.data_dir)  # mode 0600
        try:
            with os.fdopen(fd, "wb") as out:
                out.write(secrets.token_bytes(SECRET_BYTES))
            with contextlib.suppress(FileExistsError):
                os.link(temporary, path)
        finally:
            os.unlink(temporary)
    secret = path.read_bytes()
    if len(secret) != SECRET_BYTES:
        raise TokenError(f"{path}: holds {len(secret)} bytes, not a {SECRET_BYTES}-byte webhook secret (remove it to "
                         "make a new one)", status=500)
    return secret


def webhook_secret(settings: Settings, principal_name: str) -> bytes:
    """The key that signs the webhooks of work made by ``principal_name``: for ``admin`` (``VOXNERF_API_TOKEN``)
    HMAC-SHA256(key=the token, msg=b"voxnerf-webhook"); for ``local`` the random secret in
    ``<data_dir>/webhook_secret``. :class:`TokenError` (404) for any other name, and for ``admin`` while no token
    is set."""
    if principal_name == LEGACY_ADMIN:
        if settings.api_token is None:
            raise TokenError("no VOXNERF_API_TOKEN is set, so principal 'admin' has no webhook secret", status=404)
        return hmac.new(settings.api_token.get_secret_value().encode(), LEGACY_WEBHOOK_MESSAGE, hashlib.sha256).digest()
    if principal_name == LOCAL:
        return _local_webhook_secret(settings)
    raise TokenError(f"no token named {principal_name!r}, so it has no webhook secret", status=404)
