"""``voxnerf tokens create | list | revoke | show-secret``: the service's named tokens (:mod:`app.core.tokens`), on
the database its settings name (the same ``VOXNERF_*`` variables as ``voxnerf serve``). A running service sees a
change at its next request."""

from __future__ import annotations

import argparse
from datetime import datetime, timezone

from app.core import tokens
from app.core.settings import get_settings


def _when(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    return datetime.fromtimestamp(seconds, tz=timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def create(args: argparse.Namespace) -> int:
    """Make a token: a summary line, the webhook secret (labelled), then the token alone on the last line."""
    made = tokens.create_token(get_settings(), args.name, args.scope, args.max_queued)
    limit = made.max_queued if made.max_queued is not None else "the service's default"
    print(f"token {made.name!r} made: scope {made.scope}, queue limit {limit}; the token is shown only now")
    print(f"webhook secret: {made.webhook_secret}")
    print(made.token)
    return 0


def list_all(_args: argparse.Namespace) -> int:
    """One line per token (never the token itself): name, scope, queue limit, created, last used, revoked."""
    rows = [("NAME", "SCOPE", "MAX QUEUED", "CREATED", "LAST USED", "REVOKED")]
    for row in tokens.list_tokens(get_settings()):
        rows.append((row.name, row.scope, str(row.max_queued) if row.max_queued is not None else "default",
                     _when(row.created_at), _when(row.last_used_at), _when(row.revoked_at)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(r, widths, strict=True)).rstrip())
    return 0


def revoke(args: argparse.Namespace) -> int:
    row = tokens.revoke_token(get_settings(), args.name)
    print(f"token {row.name!r} revoked ({_when(row.revoked_at)}): the service refuses it from its next request")
    return 0


def show_secret(args: argparse.Namespace) -> int:
    """The token's webhook secret (hex), alone on its line."""
    print(tokens.show_secret(get_settings(), args.name))
    return 0


COMMANDS = {"create": create, "list": list_all, "revoke": revoke, "show-secret": show_secret}


def run(args: argparse.Namespace) -> int:
    """Run ``voxnerf tokens <args.tokens_command>``."""
    return COMMANDS[args.tokens_command](args)
