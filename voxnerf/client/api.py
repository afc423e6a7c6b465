"""A Python client of the VoxNeRF REST service (``voxnerf serve``; docs/service.md), and what ``voxnerf remote``
runs.

    from voxnerf.client import Client

    with Client("http://gpu-box:8000", token="...") as api:  # or VOXNERF_URL / VOXNERF_API_TOKEN
        scene = api.upload("scans/kitchen.zip")                  # a directory is zipped first
        job = api.wait(api.train(scene.id, max_seconds=300).id)  # follows GET /jobs/{id}/events
        api.render(job.id, frame="rgb/frame-000010.png", out="view.png")
        api.download(job.id, "runs/kitchen")

Answers are the API's own pydantic models (:mod:`app.schemas`: ``SceneOut``, ``JobOut``, ``OutputOut``,
``ImportOut``), and requests are checked by the models the API checks them with (``JobOptions``,
``RenderRequest``, ``VideoRequest``) before anything is sent. Every request is retried with exponential back-off
on 429 and 503 (honouring ``Retry-After``) and on connection errors; a request whose body may have arrived is
sent again only where a repeat is harmless (GET, PUT, DELETE, cancel, render) or costs little (an upload: at worst
a second copy of the scene, or an upload session left to expire), never a new training or output job. Files past
``session_threshold`` go in an upload session (``/uploads``), part by part, each part resent after a dropped
connection; smaller ones in one streamed ``POST /scenes``. Downloads stream to a temporary file renamed into place.
A refusal raises :class:`ApiError`, one line: the server's ``detail``.
"""

from __future__ import annotations

import email.utils
import hashlib
import json
import os
import random
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import httpx

from app.core.render_request import RenderRequest
from app.schemas import ImportOut, JobOptions, JobOut, OutputOut, SceneOut, VideoRequest
from voxnerf.errors import VoxNeRFError

__all__ = ["ApiError", "Client", "Event", "Progress", "DEFAULT_URL"]

DEFAULT_URL = "http://127.0.0.1:8000"
FINAL_STATES = frozenset({"succeeded", "failed", "cancelled"})
RETRY_STATUSES = frozenset({429, 503})
SAFE_TO_RESEND = frozenset({"GET", "HEAD", "PUT", "DELETE"})  # a resent one does what the first did
SESSION_THRESHOLD = 64 * 1024 * 1024
CHUNK = 1024 * 1024
Progress = Callable[[int, int | None], None]  # (bytes done, bytes in all or None when unknown)


class ApiError(VoxNeRFError):
    """The service refused a request: ``status`` (HTTP) and ``detail`` (the server's, one line)."""

    def __init__(self, status: int, detail: str) -> None:
        self.status = status
        self.detail = " ".join(detail.split())
        super().__init__(f"{self.detail} (HTTP {status})")


@dataclass(frozen=True)
class Event:
    """One Server-Sent Event of ``GET /jobs/{id}/events``: ``id`` (grows per job), ``event`` (``progress``,
    ``stage``, ``evaluation``, ``state``) and its JSON ``data``."""

    id: int | None
    event: str
    data: Any


def _detail(response: httpx.Response) -> str:
    """The ``detail`` of an error answer, as one line (FastAPI's validation list: its first entry's place and
    message)."""
    try:
        detail = response.json().get("detail")
    except (ValueError, AttributeError):
        return response.text[:500] or response.reason_phrase
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):
        first = detail[0]
        where = ".".join(str(part) for part in first.get("loc", ()) if part != "body")
        return f"{where}: {first.get('msg', '')}" if where else str(first.get("msg", ""))
    return detail if isinstance(detail, str) else json.dumps(detail)


def _retry_after(response: httpx.Response) -> float | None:
    """``Retry-After`` in seconds (a number, or an HTTP date), None when absent or unreadable."""
    value = response.headers.get("retry-after")
    if value is None:
        return None
    if value.strip().isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


def _sha256(path: Path, start: int = 0, size: int | None = None) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as source:
        source.seek(start)
        left = size
        while left is None or left > 0:
            chunk = source.read(CHUNK if left is None else min(CHUNK, left))
            if not chunk:
                break
            digest.update(chunk)
            if left is not None:
                left -= len(chunk)
    return digest.hexdigest()


class _ReadCounter:
    """A file read by httpx's multipart encoder, reporting the bytes read so far to ``progress``."""

    def __init__(self, source: BinaryIO, total: int, progress: Progress | None) -> None:
        self._source = source
        self._total = total
        self._progress = progress
        self._done = 0

    def read(self, size: int = -1) -> bytes:
        data = self._source.read(size)
        self._done += len(data)
        if self._progress is not None and data:
            self._progress(self._done, self._total)
        return data

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        position = self._source.seek(offset, whence)
        if whence == os.SEEK_SET and offset == 0:
            self._done = 0
        return position

    def tell(self) -> int:
        return self._source.tell()

    def fileno(self) -> int:
        return self._source.fileno()


class Client:
    """A session with one service. ``url`` defaults to ``VOXNERF_URL`` (else :data:`DEFAULT_URL`), ``token`` to
    ``VOXNERF_API_TOKEN``. ``retries``: attempts after the first, with back-off ``backoff_s`` x 2^n (jittered,
    at most ``max_backoff_s``; a ``Retry-After`` is honoured up to that). ``transport``: an httpx transport, for
    tests and proxies."""

    def __init__(self, url: str | None = None, token: str | None = None, *, timeout_s: float = 120.0,
                 retries: int = 6, backoff_s: float = 0.5, max_backoff_s: float = 30.0,
                 session_threshold: int = SESSION_THRESHOLD, transport: httpx.BaseTransport | None = None) -> None:
        self.url = (url or os.environ.get("VOXNERF_URL") or DEFAULT_URL).rstrip("/")
        token = token if token is not None else os.environ.get("VOXNERF_API_TOKEN") or None
        self.retries = retries
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.session_threshold = session_threshold
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout_s, transport=transport,
                                  trust_env=False)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------ requests

    def _pause(self, attempt: int, response: httpx.Response | None) -> None:
        wait = self.backoff_s * 2**attempt * (0.5 + random.random() / 2)
        if response is not None and (after := _retry_after(response)) is not None:
            wait = after
        time.sleep(min(wait, self.max_backoff_s))

    @contextmanager
    def _stream(self, method: str, path: str, *, resend: bool | None = None,
                build: Callable[[], dict] | None = None, **kwargs: Any) -> Iterator[httpx.Response]:
        """The response to ``method path``, its body not read yet, after the retries (:meth:`_send`)."""
        response = self._send(method, path, resend=resend, build=build, **kwargs)
        try:
            yield response
        finally:
            response.close()

    def _send(self, method: str, path: str, *, resend: bool | None, build: Callable[[], dict] | None,
              **kwargs: Any) -> httpx.Response:
        """Send ``method path`` until it is answered with neither 429 nor 503 and the connection holds, at most
        ``1 + retries`` times; the open response (status under 400), else ApiError. ``build()`` gives the
        request's arguments afresh for each attempt (a file read from its start); ``resend``: whether a request
        whose body may have arrived may be sent again (default: by its method)."""
        resend = method in SAFE_TO_RESEND if resend is None else resend
        attempt = 0
        while True:
            arguments = kwargs | (build() if build is not None else {})
            response = None
            try:
                response = self._http.send(self._http.build_request(method, path, **arguments), stream=True)
                if response.status_code in RETRY_STATUSES and attempt < self.retries:
                    response.read()
                    response.close()
                elif response.status_code >= 400:
                    response.read()
                    response.close()
                    raise ApiError(response.status_code, _detail(response))
                else:
                    return response
            except (httpx.ConnectError, httpx.ConnectTimeout):
                if attempt >= self.retries:
                    raise ApiError(0, f"cannot reach {self.url}: is the service running?") from None
            except httpx.TransportError as err:
                if not resend or attempt >= self.retries:
                    raise ApiError(0, f"{method} {path}: the connection failed "
                                      f"({str(err) or type(err).__name__})") from None
                response = None
            self._pause(attempt, response)
            attempt += 1

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        with self._stream(method, path, **kwargs) as response:
            response.read()
            return response.json() if response.content else None

    # ------------------------------------------------------------------------------------------ scenes

    def scenes(self) -> list[SceneOut]:
        return [SceneOut.model_validate(row) for row in self._json("GET", "/scenes")]

    def scene(self, scene_id: str) -> SceneOut:
        return SceneOut.model_validate(self._json("GET", f"/scenes/{scene_id}"))

    def upload(self, path: str | Path, *, name: str | None = None, splits: str | None = None,
               progress: Progress | None = None, wait: bool = True) -> SceneOut | ImportOut:
        """Upload a scene: a directory (zipped to a temporary file first), a zip, or a capture (a video, a ROS
        bag...). A capture's import is queued by the server (202): with ``wait`` this waits for it and returns
        the scene it made (ApiError when it failed), else the import as it is."""
        path = Path(path)
        if not path.exists():
            raise VoxNeRFError(f"{path}: no such file or directory")
        if path.is_dir():
            with tempfile.TemporaryDirectory(prefix="voxnerf-upload-") as folder:
                archive = Path(folder) / f"{path.resolve().name or 'scene'}.zip"
                _zip_directory(path, archive)
                return self.upload(archive, name=name or path.resolve().name, splits=splits, progress=progress,
                                   wait=wait)
        size = path.stat().st_size
        if size >= self.session_threshold:
            answer = self._upload_in_parts(path, size, name, splits, progress)
        else:
            answer = self._upload_at_once(path, size, name, splits, progress)
        if "layout" in answer:  # 202: a queued import
            queued = ImportOut.model_validate(answer)
            return self.wait_import(queued.id) if wait else queued
        return SceneOut.model_validate(answer)

    def _upload_at_once(self, path: Path, size: int, name: str | None, splits: str | None,
                        progress: Progress | None) -> dict:
        fields = {key: value for key, value in (("name", name), ("splits", splits)) if value}
        with open(path, "rb") as source:
            def build() -> dict:
                source.seek(0)
                reader = _ReadCounter(source, size, progress)
                return {"files": {"file": (path.name, reader, "application/octet-stream")}, "data": fields}

            return self._json("POST", "/scenes", build=build, resend=True)

    def _upload_in_parts(self, path: Path, size: int, name: str | None, splits: str | None,
                         progress: Progress | None) -> dict:
        body = {"filename": path.name, "total_bytes": size, "sha256": _sha256(path), "name": name, "splits": splits}
        session = self._json("POST", "/uploads", json={k: v for k, v in body.items() if v is not None}, resend=True)
        return self.resume_upload(session["id"], path, progress)

    def resume_upload(self, upload_id: str, path: str | Path, progress: Progress | None = None) -> dict:
        """Send the parts of upload session ``upload_id`` it has not received (``GET /uploads/{id}``) from the
        file ``path``, then complete it; the JSON ``POST /uploads/{id}/complete`` answers (a scene or an
        import). Each part is resent, from its start, after a dropped connection."""
        path = Path(path)
        state = self._json("GET", f"/uploads/{upload_id}")
        part_bytes, total = state["part_bytes"], state["total_bytes"]
        received = set(state["received_parts"])
        done = state["received_bytes"]
        for number in range(state["part_count"]):
            if number not in received:
                size = min(part_bytes, total - number * part_bytes)
                self._send_part(upload_id, path, number, number * part_bytes, size, (done, total), progress)
                done += size
        return self._json("POST", f"/uploads/{upload_id}/complete", resend=False)

    def _send_part(self, upload_id: str, path: Path, number: int, start: int, size: int,
                   before: tuple[int, int], progress: Progress | None) -> None:
        """PUT part ``number`` (``size`` bytes of ``path`` from ``start``), streamed; ``before``: the bytes the
        session had before it and the file's size, for ``progress``."""
        digest = _sha256(path, start, size)
        base, total = before

        def body() -> Iterator[bytes]:
            with open(path, "rb") as source:
                source.seek(start)
                left = size
                while left:
                    chunk = source.read(min(CHUNK, left))
                    if not chunk:
                        raise VoxNeRFError(f"{path}: the file became shorter while it was uploaded")
                    left -= len(chunk)
                    if progress is not None:
                        progress(base + size - left, total)
                    yield chunk

        headers = {"Content-Length": str(size), "X-Content-SHA256": digest, "Content-Type": "application/octet-stream"}
        self._json("PUT", f"/uploads/{upload_id}/parts/{number}", build=lambda: {"content": body(), "headers": headers})

    def wait_import(self, import_id: str, *, timeout_s: float | None = None, interval_s: float = 1.0) -> SceneOut:
        """Wait for a capture's import (``GET /imports/{id}``, which has no event stream) and return its scene;
        ApiError when it failed or was cancelled."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            row = ImportOut.model_validate(self._json("GET", f"/imports/{import_id}"))
            if row.state == "succeeded":
                return self.scene(row.scene_id)
            if row.state in FINAL_STATES:
                raise VoxNeRFError(f"import {import_id} {row.state}: {row.error or 'no reason given'}")
            if deadline is not None and time.monotonic() > deadline:
                raise ApiError(0, f"import {import_id} is still {row.state} after {timeout_s:.0f} s")
            time.sleep(interval_s)

    # ------------------------------------------------------------------------------------------ jobs

    def train(self, scene_id: str, **options: Any) -> JobOut:
        """Start training ``scene_id`` with the job options (``max_seconds``, ``max_iters``, ``preset``...: those
        of ``POST /scenes/{id}/jobs``, checked by its model ``JobOptions`` first: a pydantic ValidationError)."""
        body = JobOptions(**options).model_dump(mode="json", exclude_unset=True)
        return JobOut.model_validate(self._json("POST", f"/scenes/{scene_id}/jobs", json=body, resend=False))

    def job(self, job_id: str) -> JobOut:
        return JobOut.model_validate(self._json("GET", f"/jobs/{job_id}"))

    def jobs(self, scene_id: str | None = None, limit: int = 100) -> list[JobOut]:
        params = {"limit": limit} | ({"scene_id": scene_id} if scene_id else {})
        return [JobOut.model_validate(row) for row in self._json("GET", "/jobs", params=params)]

    def cancel(self, job_id: str) -> JobOut:
        return JobOut.model_validate(self._json("POST", f"/jobs/{job_id}/cancel", resend=True))

    def events(self, job_id: str, last_event_id: int | None = None) -> Iterator[Event]:
        """The job's events (``GET /jobs/{id}/events``) until its final ``state`` event; a dropped stream is
        reopened after the last event received (``Last-Event-ID``)."""
        failures = 0
        while True:
            headers = {"Accept": "text/event-stream"}
            if last_event_id is not None:
                headers["Last-Event-ID"] = str(last_event_id)
            try:
                with self._stream("GET", f"/jobs/{job_id}/events", headers=headers,
                                  timeout=httpx.Timeout(30.0, read=300.0)) as response:
                    for event in _parse_events(response.iter_lines()):
                        failures = 0
                        if event.id is not None:
                            last_event_id = event.id
                        yield event
                        if event.event == "state" and isinstance(event.data, dict) \
                                and event.data.get("state") in FINAL_STATES:
                            return
            except (httpx.TransportError, httpx.StreamError):
                pass  # dropped mid-stream: reopen where it stopped
            failures += 1
            if failures > self.retries:
                raise ApiError(0, f"the event stream of job {job_id} kept closing before the job ended")
            self._pause(failures - 1, None)

    def wait(self, job_id: str, *, on_event: Callable[[Event], None] | None = None,
             timeout_s: float | None = None) -> JobOut:
        """Follow the job's events until it is succeeded, failed or cancelled; the job then (check its
        ``state``). ``on_event`` sees each event. A service without the event stream (404 for the route
        itself) is asked ``GET /jobs/{id}`` every second instead."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        try:
            for event in self.events(job_id):
                if on_event is not None:
                    on_event(event)
                if event.event == "state" and event.data.get("state") in FINAL_STATES:
                    return JobOut.model_validate(event.data)
                if deadline is not None and time.monotonic() > deadline:
                    break
        except ApiError as err:
            if not (err.status == 404 and err.detail == "Not Found"):  # FastAPI's answer for an unknown route
                raise
            return self._poll_job(job_id, deadline)
        return self._poll_job(job_id, deadline)

    def _poll_job(self, job_id: str, deadline: float | None) -> JobOut:
        while (job := self.job(job_id)).state not in FINAL_STATES:
            if deadline is not None and time.monotonic() > deadline:
                raise ApiError(0, f"job {job_id} is still {job.state}: the wait timed out")
            time.sleep(1.0)
        return job

    # ------------------------------------------------------------------------------------------ renders, outputs

    def render(self, job_id: str, *, frame: str | None = None, pose: dict | None = None,
               out: str | Path | None = None, **request: Any) -> bytes:
        """Render a view of a finished job: the scene's camera ``frame`` (its file_path, file name or stem; its
        undistorted view), or ``pose`` (``transform_matrix`` and optional intrinsics, as ``POST /render``'s
        body), with ``POST /render``'s other fields (``width``, ``height``, ``format``, ``outputs``...). The
        image's bytes, also written to ``out`` when given."""
        if (frame is None) == (pose is None):
            raise VoxNeRFError("render: give frame or pose (one of them)")
        view = self._frame_view(job_id, frame, request) if frame is not None else dict(pose)
        body = RenderRequest(job_id=job_id, **(request | view)).model_dump(mode="json", exclude_none=True)
        data = self._json_bytes("POST", "/render", json=body, resend=True)
        if out is not None:
            _write_atomically(Path(out), data)
        return data

    def _frame_view(self, job_id: str, name: str, request: dict) -> dict:
        cameras = self._json("GET", f"/jobs/{job_id}/cameras")["frames"]
        matches = [c for c in cameras if name in (c["name"], Path(c["name"]).name, Path(c["name"]).stem)]
        if len(matches) != 1:
            examples = ", ".join(c["name"] for c in (matches or cameras)[:3])
            what = f"names {len(matches)} frames" if matches else "names no frame"
            raise VoxNeRFError(f"--frame: {name!r} {what} of job {job_id}'s scene (give a file_path, e.g. {examples})")
        camera = matches[0]
        width, height = request.get("width") or camera["width"], request.get("height") or camera["height"]
        sx, sy = width / camera["width"], height / camera["height"]  # another size scales the frame's camera
        return {"transform_matrix": camera["transform_matrix"], "width": width, "height": height,
                "fl_x": camera["fl_x"] * sx, "cx": camera["cx"] * sx, "fl_y": camera["fl_y"] * sy,
                "cy": camera["cy"] * sy}

    def _json_bytes(self, method: str, path: str, **kwargs: Any) -> bytes:
        with self._stream(method, path, **kwargs) as response:
            return response.read()

    def video(self, job_id: str, *, wait: bool = True, out: str | Path | None = None,
              progress: Progress | None = None, **request: Any) -> OutputOut:
        """Queue a video of a finished job (``POST /jobs/{id}/videos`` with ``VideoRequest``'s fields: ``path``
        and ``frames``, or ``camera_path``...). With ``wait``, wait for it (``GET /outputs/{id}``) and, when it
        succeeded and ``out`` is given, download the MP4 there."""
        body = VideoRequest(**request).model_dump(mode="json", exclude_none=True)
        output = OutputOut.model_validate(self._json("POST", f"/jobs/{job_id}/videos", json=body, resend=False))
        if not wait:
            return output
        output = self.wait_output(output.id)
        if output.state != "succeeded":
            raise VoxNeRFError(f"video {output.id} {output.state}: {output.error or 'no reason given'}")
        if out is not None:
            self.download_file(f"/outputs/{output.id}/file", Path(out), progress)
        return output

    def wait_output(self, output_id: str, *, interval_s: float = 1.0) -> OutputOut:
        """Wait for an output job (``GET /outputs/{id}``) to be final; the output then."""
        while (output := OutputOut.model_validate(self._json("GET", f"/outputs/{output_id}"))).state \
                not in FINAL_STATES:
            time.sleep(interval_s)
        return output

    def outputs(self, job_id: str) -> list[OutputOut]:
        return [OutputOut.model_validate(row) for row in self._json("GET", f"/jobs/{job_id}/outputs")]

    def download_file(self, url_path: str, target: Path, progress: Progress | None = None) -> Path:
        """Stream ``GET url_path`` into ``target`` (a temporary file beside it, renamed once complete)."""
        target.parent.mkdir(parents=True, exist_ok=True)
        with self._stream("GET", url_path) as response:
            length = response.headers.get("content-length")
            total = int(length) if length and length.isdigit() else None
            handle, temp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
            try:
                with os.fdopen(handle, "wb") as sink:
                    done = 0
                    for chunk in response.iter_bytes(CHUNK):
                        sink.write(chunk)
                        done += len(chunk)
                        if progress is not None:
                            progress(done, total)
                os.replace(temp, target)
            except BaseException:
                Path(temp).unlink(missing_ok=True)
                raise
        return target

    def download(self, job_id: str, out_dir: str | Path, progress: Progress | None = None) -> list[Path]:
        """Download a finished job's run into ``out_dir``: ``report.json``, ``checkpoint.pt`` (what ``voxnerf
        render`` reads from a run directory), its evaluation renders (``eval/<split>/<name>.png``) and the files
        of its succeeded outputs (``outputs/<id>-<name>``); the paths written. A file the run never wrote (a job
        that failed before training) is left out."""
        job = self.job(job_id)
        if job.state not in FINAL_STATES:
            raise VoxNeRFError(f"job {job_id} is {job.state}: its run is downloaded once it has ended")
        out = Path(out_dir)
        wanted = [(f"/jobs/{job_id}/report", out / "report.json"),
                  (f"/jobs/{job_id}/checkpoint", out / "checkpoint.pt")]
        for render in self._json("GET", f"/jobs/{job_id}/renders"):
            wanted.append((render["url"], out / "eval" / render["split"] / f"{render['name']}.png"))
        for output in self.outputs(job_id):
            if output.state == "succeeded" and output.file_url:
                wanted.append((output.file_url, out / "outputs" / f"{output.id}-{output.file_name}"))
        written = []
        for url_path, target in wanted:
            try:
                written.append(self.download_file(url_path, target, progress))
            except ApiError as err:
                if err.status != 404:
                    raise
        return written


def _parse_events(lines: Iterator[str]) -> Iterator[Event]:
    """Server-Sent Events from a stream's lines (the WHATWG rules: ``field: value`` lines, ``data`` lines
    joined, a blank line ends an event, ``:`` a comment)."""
    fields: dict[str, str] = {}
    data: list[str] = []
    for line in lines:
        if not line:
            if data:
                event_id = fields.get("id", "")
                yield Event(int(event_id) if event_id.isdigit() else None, fields.get("event", "message"),
                            json.loads("\n".join(data)))
            fields, data = {}, []
            continue
        if line.startswith(":"):
            continue
        key, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if key == "data":
            data.append(value)
        elif key in ("id", "event"):
            fields[key] = value


def _zip_directory(folder: Path, archive: Path) -> None:
    """Zip every file under ``folder`` (paths relative to it; hidden files left out) into ``archive``."""
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as out:
        for path in sorted(folder.rglob("*")):
            relative = path.relative_to(folder)
            if path.is_file() and not any(part.startswith(".") for part in relative.parts):
                out.write(path, relative.as_posix())


def _write_atomically(target: Path, data: bytes) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    temp = target.with_name(f".{target.name}.partial")
    temp.write_bytes(data)
    os.replace(temp, target)
