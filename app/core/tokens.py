"""The webhook signing secret of a principal (who made a job): the key of its deliveries' HMAC signatures.

Only the principals that exist without named tokens are known here: ``admin`` (the holder of ``VOXNERF_API_TOKEN``,
whose secret is derived from the token, so it changes when the token does) and ``local`` (a tokenless service's
loopback clients, whose secret is a random file ``<data_dir>/webhook_secret`` made once, readable by its owner
only). Named tokens, each with a secret of its own, extend :func:`webhook_secret`.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets

from app.core.settings import Settings

LEGACY_ADMIN = "admin"  # the principal of VOXNERF_API_TOKEN
TOKENLESS = "local"  # the principal of a tokenless service's loopback clients
SECRET_FILE = "webhook_secret"
SECRET_BYTES = 32


class UnknownPrincipal(LookupError):
    """No webhook secret exists for the principal (its token was revoked, or the token setting changed)."""


def _tokenless_secret(settings: Settings) -> bytes:
    """The random secret in ``<data_dir>/webhook_secret`` (hex), made with mode 0600 by whichever process needs it
    first (an exclusive create, so concurrent processes agree on one)."""
    path = settings.data_dir / SECRET_FILE
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        text = path.read_text().strip()
        if len(text) != 2 * SECRET_BYTES:
            raise UnknownPrincipal(f"{path} does not hold a webhook secret ({2 * SECRET_BYTES} hex digits)") from None
        return bytes.fromhex(text)
    secret = secrets.token_bytes(SECRET_BYTES)
    with os.fdopen(fd, "w") as file:
        file.write(secret.hex())
    return secret


def webhook_secret(settings: Settings, principal_name: str) -> bytes:
    """The key that signs the webhooks of jobs made by ``principal_name``: for ``admin`` (the API token's holder)
    HMAC-SHA256(key=VOXNERF_API_TOKEN, msg=b"voxnerf-webhook"); for ``local`` (no token set) the random secret in
    ``<data_dir>/webhook_secret``. Raises :class:`UnknownPrincipal` for any other name, or for ``admin`` while no
    token is set."""
    if principal_name == LEGACY_ADMIN and settings.api_token is not None:
        return hmac.new(settings.api_token.get_secret_value().encode(), b"voxnerf-webhook", hashlib.sha256).digest()
    if principal_name == TOKENLESS and settings.api_token is None:
        return _tokenless_secret(settings)
    raise UnknownPrincipal(f"no webhook secret for principal {principal_name!r}")
