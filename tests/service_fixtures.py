"""Real service processes for the service tests, all on 127.0.0.1: uvicorn, Celery workers, redis-server.

Every process runs in its own process group with its output in a log file, and is stopped (SIGTERM, then
SIGKILL) by :meth:`Service.stop`. Nothing listens beyond loopback.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
PYTHON = sys.executable
T = TypeVar("T")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for(check: Callable[[], T], timeout_s: float, what: str, interval_s: float = 0.2) -> T:
    """Poll ``check()`` until it returns something truthy; AssertionError naming ``what`` on timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(interval_s)


def _start(cmd: list[str], log_path: Path, env: dict[str, str], cwd: Path = REPO) -> subprocess.Popen:
    """Start ``cmd`` in a new process group, stdout and stderr appended to ``log_path``."""
    with open(log_path, "ab") as log:  # the child keeps its own descriptor
        return subprocess.Popen(
            cmd, cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
        )


def stop_process(proc: subprocess.Popen, grace_s: float = 10.0, kill: bool = False) -> None:
    """SIGTERM the process (SIGKILL its group at once when ``kill``), wait up to ``grace_s``, then SIGKILL
    whatever is left of its process group."""
    if proc.poll() is None:
        if kill:
            os.killpg(proc.pid, signal.SIGKILL)
        else:
            proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(grace_s)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)


@dataclass
class RedisServer:
    """A redis-server on a fixed loopback port and directory, so that it can be stopped and started again.

    With ``appendonly`` every write goes to the append-only file in ``work_dir`` (fsync every second, as in
    docker-compose.yml) and a restarted server reloads it; without it nothing is persisted.
    """

    work_dir: Path
    port: int
    appendonly: bool = False
    proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def ping(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5) as sock:
                sock.sendall(b"PING\r\n")
                return sock.recv(16).startswith(b"+PONG")
        except OSError:
            return False

    def start(self) -> None:
        """Start the server (again) on the same port and directory; waits until it answers PING."""
        if self.proc is not None and self.proc.poll() is None:
            raise RuntimeError(f"redis-server on port {self.port} is already running")
        self.proc = _start(
            [
                "redis-server",
                "--bind",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--dir",
                str(self.work_dir),
                "--save",
                "",
                "--appendonly",
                "yes" if self.appendonly else "no",
                "--appendfsync",
                "everysec",
                "--protected-mode",
                "yes",
            ],
            self.work_dir / "redis.log",
            dict(os.environ),
        )
        wait_for(self.ping, 20, f"redis-server on port {self.port} to answer PING")

    def stop(self) -> None:
        """SIGTERM: redis-server flushes its append-only file and exits (``SHUTDOWN``)."""
        if self.proc is not None:
            stop_process(self.proc)
            self.proc = None


def start_redis(work_dir: Path, appendonly: bool = False) -> RedisServer:
    """A redis-server on a free loopback port with its files in ``work_dir`` (see :class:`RedisServer`)."""
    if shutil.which("redis-server") is None:
        raise RuntimeError("redis-server is not installed (scripts/install.sh installs it)")
    work_dir.mkdir(parents=True, exist_ok=True)
    server = RedisServer(work_dir, free_port(), appendonly)
    server.start()
    return server


@dataclass
class Service:
    """An API server and its workers, configured only through ``VOXNERF_*`` environment variables."""

    root: Path
    env: dict[str, str]
    port: int
    token: str | None
    mode: str = "embedded"  # or "redis": which broker the processes use
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def data_dir(self) -> Path:
        return Path(self.env["VOXNERF_DATA_DIR"])

    def client(self, auth: bool = True, timeout_s: float = 60.0) -> httpx.Client:
        headers = {"Authorization": f"Bearer {self.token}"} if auth and self.token else {}
        return httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout_s, trust_env=False)

    def start_api(self) -> None:
        self.procs["api"] = _start(
            [
                PYTHON,
                "-m",
                "uvicorn",
                "--factory",
                "app.main:create_app",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--log-level",
                "warning",
            ],
            self.root / "api.log",
            self.env,
        )

    def start_worker(self, queue: str, name: str | None = None, env: dict[str, str] | None = None) -> None:
        """A worker process (concurrency 1) on ``queue``, known as ``name`` (default: the queue's name) in
        ``procs`` and logging to ``worker-<name>.log``; ``env`` adds to (or replaces) the service's variables."""
        name = name or queue
        self.procs[name] = _start(
            [PYTHON, "-m", "worker", "--queues", queue, "--concurrency", "1"],
            self.root / f"worker-{name}.log",
            {**self.env, **(env or {})},
        )

    def restart_api(self) -> None:
        """Stop the API process (SIGTERM, as a deployment would) and start it again on the same port."""
        stop_process(self.procs.pop("api"))
        self.start_api()
        wait_for(self.answers, 60, "the restarted API to answer")

    def kill(self, name: str) -> None:
        """SIGKILL a process group at once (a crash, not a shutdown)."""
        stop_process(self.procs.pop(name), kill=True)

    def answers(self) -> bool:
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}  # the schema is behind the token
        try:
            return httpx.get(f"{self.base_url}/openapi.json", headers=headers, timeout=5,
                             trust_env=False).status_code == 200
        except httpx.HTTPError:
            return False

    def wait_healthy(self, timeout_s: float = 120.0) -> dict:
        """Poll GET /healthz (with the token, for the details) until 200; its JSON."""
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}

        def healthy():
            try:
                response = httpx.get(f"{self.base_url}/healthz", headers=headers, timeout=5, trust_env=False)
            except httpx.HTTPError:
                return None
            return response.json() if response.status_code == 200 else None

        return wait_for(
            healthy, timeout_s, "GET /healthz to answer 200 (API, broker and both workers up)", 0.5
        )

    def logs(self) -> str:
        """The tail of every process's log, for failure messages."""
        parts = []
        for path in sorted(self.root.glob("*.log")):
            parts.append(f"----- {path.name}\n{path.read_text(errors='replace')[-4000:]}")
        return "\n".join(parts)

    def stop(self) -> None:
        """Tear the service down: SIGKILL every process group at once. An idle worker's warm shutdown takes
        seconds (Celery's loop wakes, the pool's process is joined), which every test's teardown would pay; warm
        shutdowns are test_serve_signals.py's subject (and :meth:`restart_api`'s)."""
        for name in list(self.procs):
            stop_process(self.procs.pop(name), kill=True)


def start_service(
    root: Path,
    *,
    broker_url: str | None = None,
    token: str | None = None,
    settings: dict[str, str] | None = None,
    workers: bool = True,
) -> Service:
    """API + one train worker + one render worker (unless ``workers`` is False) on a fresh data directory in
    ``root``; waits until /healthz is 200 (without workers: until the API answers)."""
    root.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    env.update(
        {
            "VOXNERF_DATA_DIR": str(root / "data"),
            "VOXNERF_DEVICE": "cpu",
            "VOXNERF_SWEEP_INTERVAL_S": "1",
            "VOXNERF_HEALTH_TIMEOUT_S": "2",
            # a task loads the engine when it first runs: most tests' workers run one kind of task, or none
            "VOXNERF_WORKER_PRELOAD": "0",
            "PYTHONPATH": str(REPO),
            "PYTHONUNBUFFERED": "1",
            "NO_PROXY": "127.0.0.1,localhost",
        }
    )
    if broker_url:
        env["VOXNERF_BROKER_URL"] = broker_url
    if token:
        env["VOXNERF_API_TOKEN"] = token
    env.update(settings or {})
    service = Service(root, env, free_port(), token, "redis" if broker_url else "embedded")
    try:
        service.start_api()
        if workers:
            service.start_worker("train")
            service.start_worker("render")
            service.wait_healthy()
        else:
            wait_for(service.answers, 60, "the API to answer")
    except BaseException:
        print(service.logs())
        service.stop()
        raise
    return service


def zip_scene(
    scene_dir: Path, top_folder: str | None = "room", skip: tuple[str, ...] = ("gt_mesh.ply",)
) -> bytes:
    """The bytes of a .zip of ``scene_dir`` (under one top-level folder, as most archivers write it)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(scene_dir.rglob("*")):
            rel = path.relative_to(scene_dir).as_posix()
            if path.is_file() and rel not in skip:
                archive.write(path, f"{top_folder}/{rel}" if top_folder else rel)
    return buffer.getvalue()


def upload_scene(client: httpx.Client, scene_dir: Path) -> dict:
    """POST ``scene_dir`` as a .zip to /scenes; the created scene's JSON (asserts 201)."""
    response = client.post("/scenes", files={"file": ("room.zip", zip_scene(scene_dir), "application/zip")})
    assert response.status_code == 201, response.text
    return response.json()


def wait_until_succeeded(service: Service, client: httpx.Client, job_id: str, timeout_s: float) -> dict:
    """Poll GET /jobs/{id} until the job succeeded; its JSON. AssertionError with the service's logs when it
    failed, was cancelled, or did not succeed within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while (job := client.get(f"/jobs/{job_id}").json())["state"] != "succeeded":
        if job["state"] in ("failed", "cancelled") or time.monotonic() > deadline:
            raise AssertionError(f"job {job_id} is {job['state']} ({job['error']})\n{service.logs()}")
        time.sleep(0.5)
    return job


FINAL_STATES = ("succeeded", "failed", "cancelled")


def wait_until_final(service: Service, client: httpx.Client, path: str, timeout_s: float) -> dict:
    """Poll ``GET path`` (a job, output or import) until its state is final; its JSON. The test fails with the
    service's logs when it is not final within ``timeout_s``."""
    try:
        return wait_for(lambda: (row := client.get(path).json())["state"] in FINAL_STATES and row, timeout_s,
                        f"{path} to finish", 0.5)
    except AssertionError:
        pytest.fail(f"{path} did not finish\n{service.logs()}")


def first_pose(scene_dir: Path, split_key: str = "test_filenames") -> list[list[float]]:
    """The transform_matrix of the first frame of a split (a pose the model has not trained on)."""
    meta = json.loads((scene_dir / "transforms.json").read_text())
    wanted = meta[split_key][0]
    return next(f["transform_matrix"] for f in meta["frames"] if f["file_path"] == wanted)
