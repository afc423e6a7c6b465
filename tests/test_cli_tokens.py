"""``voxnerf tokens create | list | revoke | show-secret`` as a user runs them: subprocesses on a data directory named
by ``VOXNERF_DATA_DIR``, as ``voxnerf serve`` would read it; the tokens they make are checked against the service's
own resolution (:func:`app.core.tokens.resolve`)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from app.core import tokens
from app.core.settings import Settings

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def data_dir(tmp_path) -> Path:
    return tmp_path / "data"


def _voxnerf(data_dir: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    env.update({"VOXNERF_DATA_DIR": str(data_dir), "PYTHONPATH": str(REPO)})
    return subprocess.run([sys.executable, "-m", "voxnerf", "tokens", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)


def test_create_prints_the_token_last_and_list_never_shows_it(data_dir):
    made = _voxnerf(data_dir, "create", "ci-bot", "--scope", "write", "--max-queued", "3")
    assert made.returncode == 0, made.stderr
    lines = made.stdout.strip().splitlines()
    token = lines[-1]
    assert re.fullmatch(r"vxn_[A-Za-z0-9_-]{43}", token), lines
    label, _, secret = lines[-2].partition(": ")
    assert label == "webhook secret" and re.fullmatch(r"[0-9a-f]{64}", secret), lines
    assert "scope write" in lines[0] and "queue limit 3" in lines[0]

    settings = Settings(_env_file=None, data_dir=data_dir)
    assert tokens.resolve(settings, f"Bearer {token}") == tokens.Principal("ci-bot", "write", 3)

    listed = _voxnerf(data_dir, "list")
    assert listed.returncode == 0, listed.stderr
    header, row = listed.stdout.strip().splitlines()
    assert header.split() == ["NAME", "SCOPE", "MAX", "QUEUED", "CREATED", "LAST", "USED", "REVOKED"]
    assert row.split()[:3] == ["ci-bot", "write", "3"] and row.endswith("-")  # used, not revoked
    assert token not in listed.stdout and token[4:] not in listed.stdout and secret not in listed.stdout

    shown = _voxnerf(data_dir, "show-secret", "ci-bot")
    assert shown.returncode == 0 and shown.stdout.strip() == secret

    revoked = _voxnerf(data_dir, "revoke", "ci-bot")
    assert revoked.returncode == 0 and "revoked" in revoked.stdout
    assert tokens.resolve(settings, f"Bearer {token}") is None
    assert "UTC" in _voxnerf(data_dir, "list").stdout.strip().splitlines()[1].rsplit("  ", 1)[-1]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("create", "Bad Name", "--scope", "read"), "token name 'Bad Name': use 1 to 64 lowercase letters"),
        (("create", "admin", "--scope", "read"), "token name 'admin' is reserved"),
        (("revoke", "nobody"), "no token named 'nobody'"),
        (("show-secret", "nobody"), "no token named 'nobody'"),
    ],
)
def test_bad_requests_are_one_line_errors(data_dir, args, message):
    result = _voxnerf(data_dir, *args)
    assert result.returncode == 2 and result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("voxnerf: error: ") and message in lines[0], lines


def test_a_name_is_never_given_twice_and_flags_are_checked(data_dir):
    assert _voxnerf(data_dir, "create", "once", "--scope", "read").returncode == 0
    assert _voxnerf(data_dir, "revoke", "once").returncode == 0
    again = _voxnerf(data_dir, "create", "once", "--scope", "admin")
    assert again.returncode == 2 and "a token named 'once' exists already" in again.stderr
    assert _voxnerf(data_dir, "create", "x", "--scope", "root").returncode == 2  # argparse: not a scope
    assert _voxnerf(data_dir, "create", "x", "--scope", "read", "--max-queued", "0").returncode == 2
    assert [t.name for t in tokens.list_tokens(Settings(_env_file=None, data_dir=data_dir))] == ["once"]
