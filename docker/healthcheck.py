"""Container health checks: ``python healthcheck.py api [--url URL]`` or ``python healthcheck.py worker``.

Exit status 0 when healthy, 1 otherwise (the reason on stderr).

* ``api``: ``GET /healthz`` of this container answers, with 200 or with 503, and its database check is ok.
  The request carries ``VOXNERF_API_TOKEN`` from the environment when set (without it /healthz tells only
  ok or unavailable).
  A 503 that only reports a missing broker or missing workers still counts as healthy: the API process
  works and says what is missing; the workers have their own health checks.
* ``worker``: a Celery ``ping`` broadcast over the configured broker gets a reply from a worker node on this
  container's host name (node names end in ``@<hostname>``, see ``worker.run.worker_name``), over the Celery
  app of ``app.core.celery_app`` (built from the container's ``VOXNERF_*`` settings).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import urllib.error
import urllib.request


def check_api(url: str, timeout_s: float, token: str | None = None) -> str | None:
    """None when ``url`` (the /healthz endpoint) answers 200 or 503 with ``database.ok``; else the reason.
    ``token``: the API token, sent as a bearer token when given (needed for the database check's details)."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout_s) as response:
            body = json.load(response)
    except urllib.error.HTTPError as err:
        if err.code != 503:
            return f"{url} answered HTTP {err.code}"
        body = json.load(err)
    except (OSError, ValueError) as err:
        return f"{url}: {err}"
    database = body.get("database") or {}
    if not database.get("ok"):
        return f"{url}: database not ok: {database.get('detail')}"
    return None


def check_worker(timeout_s: float) -> str | None:
    """None when a Celery worker on this host answers ``ping`` within ``timeout_s``; else the reason."""
    from app.core.celery_app import get_celery

    host = socket.gethostname()
    replies = get_celery().control.ping(timeout=timeout_s)
    names = sorted(name for reply in replies for name in reply)
    if any(name.endswith(f"@{host}") for name in names):
        return None
    return f"no worker on host {host} answered ping (replies from: {names or 'none'})"


def main() -> int:
    parser = argparse.ArgumentParser(description="VoxNeRF container health check")
    parser.add_argument("role", choices=["api", "worker"])
    parser.add_argument("--url", default="http://127.0.0.1:8000/healthz", help="api: the /healthz URL")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for an answer")
    args = parser.parse_args()
    if args.role == "api":
        problem = check_api(args.url, args.timeout, os.environ.get("VOXNERF_API_TOKEN") or None)
    else:
        problem = check_worker(args.timeout)
    if problem:
        print(problem, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
