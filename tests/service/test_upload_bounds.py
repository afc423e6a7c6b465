"""Uploads bounded in memory and CPU (issue #22, item 3), with crafted files against a real API process.

A uvicorn API (``start_service``, no workers) with a small validation memory budget takes: a 200 MB
``transforms.json`` in a zip and as a form part, a zip of 10^6 empty entries, a PNG named ``.ply``, a
decompression bomb, a scene whose images sum past the scene's pixel limit, and a ``transforms.json`` whose
parsing needs more memory than the validation process may have. Each is refused with a 4xx JSON ``detail``
while the API process's peak resident memory (``VmHWM``, reset through ``/proc/<pid>/clear_refs`` before each
upload) stays within ``API_GROWTH`` of where it was, and while one is validated the API lists scenes and
refuses a second upload with 429. The end-of-central-directory reader and the validation process's time limit
and death are tested directly, in this process.
"""

from __future__ import annotations

import io
import json
import os
import signal
import struct
import threading
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_fixtures import Service, start_service, wait_for
from test_fuzz_upload import _png, _png_header_only, _zip

from app.core.settings import Settings
from app.uploads.rules import StagedUpload, UploadError
from app.uploads.sandbox import validate_in_child
from app.uploads.validation import DirectoryExtent, check_directory_extent, read_directory_extent
from voxnerf.synthetic import RoomSpec, make_room_scene

MiB = 1024 * 1024
API_GROWTH = 64 * MiB  # what one hostile upload may add to the API process's resident memory at its peak
MILLION = 1_000_000
BIG_JSON_BYTES = 200 * 1000 * 1000
EMPTY_LISTS = 12_000_000  # "[[],[],...]": ~1 GB of list objects once parsed, 36 MB of text
SERVICE_SETTINGS = {
    "VOXNERF_MAX_IMAGE_PIXELS": "1000000",
    "VOXNERF_MAX_SCENE_PIXELS": "40000",  # the 32x24 room's 8 images and 8 depth maps hold 12 288
    "VOXNERF_MAX_COMPRESSION_RATIO": "1000000",  # so that the size rules, not the zip-bomb rule, answer
    "VOXNERF_UPLOAD_VALIDATION_MEMORY_BYTES": str(512 * MiB),
    "VOXNERF_MAX_CONCURRENT_UPLOADS": "1",
}

# ------------------------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def room_files(tmp_path_factory) -> dict[str, bytes]:
    """A valid 8-frame 32x24 scene: path inside the scene -> bytes (as tests/service/test_fuzz_upload.py makes it)."""
    scene_dir = tmp_path_factory.mktemp("bounds") / "room"
    make_room_scene(
        scene_dir,
        RoomSpec(width=32, height=24, n_frames=8, train_every=2, n_gaps=0, gap_len=0, prior_max_points=2000,
                 supersample=1),
    )
    return {
        p.relative_to(scene_dir).as_posix(): p.read_bytes()
        for p in sorted(scene_dir.rglob("*"))
        if p.is_file() and p.name != "gt_mesh.ply"
    }


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Iterator[Service]:
    svc = start_service(tmp_path_factory.mktemp("bounds-service"), settings=SERVICE_SETTINGS, workers=False)
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture(scope="module")
def client(service: Service) -> Iterator[httpx.Client]:
    with service.client(timeout_s=300) as c:
        yield c


@pytest.fixture(scope="module")
def million_entry_zip(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("crafted") / "million.zip"
    _write_empty_entries_zip(path, MILLION)
    return path


# ------------------------------------------------------------------------------------------------ helpers

LOCAL_HEADER = struct.Struct("<4s5H3L2H")
DIRECTORY_RECORD = struct.Struct("<4s6H3L5H2L")
DOS_DATE = 0x21  # 1980-01-01


def _write_empty_entries_zip(path: Path, count: int, declared: int | None = None, zip64: bool = True) -> None:
    """A stored zip of ``count`` empty entries named by hex numbers, each with its local header and directory
    record, ended by zip64 records (``zip64``) or only the classic record, which declares ``declared`` entries
    (default ``count``; the classic record's 16-bit fields say 0xFFFF under zip64)."""
    names = [f"{i:05x}".encode() for i in range(count)]
    headers = [LOCAL_HEADER.pack(b"PK\x03\x04", 20, 0, 0, 0, DOS_DATE, 0, 0, 0, len(n), 0) + n for n in names]
    offsets = np.cumsum([0] + [len(h) for h in headers[:-1]]).tolist()
    start = sum(len(h) for h in headers)
    records = b"".join(
        DIRECTORY_RECORD.pack(b"PK\x01\x02", 20, 20, 0, 0, 0, DOS_DATE, 0, 0, 0, len(n), 0, 0, 0, 0, 0, at) + n
        for n, at in zip(names, offsets, strict=True)
    )
    declared = count if declared is None else declared
    if zip64:
        end = struct.pack("<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, declared, declared, len(records), start)
        end += struct.pack("<4sLQL", b"PK\x06\x07", 0, start + len(records), 1)
        end += struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    else:
        end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, declared, declared, len(records), start, 0)
    with open(path, "wb") as f:
        f.write(b"".join(headers))
        f.write(records)
        f.write(end)


def _bomb_png(side: int) -> bytes:
    """A 1-bit grayscale PNG of ``side`` x ``side`` zeros: a few kB that decode to ``side``^2 bytes or more."""
    ihdr = struct.pack(">IIBBBBB", side, side, 1, 0, 0, 0, 0)
    row = bytes(1 + (side + 7) // 8)
    packer = zlib.compressobj(9)
    idat = b"".join(packer.compress(row) for _ in range(side)) + packer.flush()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _memory_kib(pid: int) -> dict[str, int]:
    """``VmRSS`` and ``VmHWM`` (peak) of a process, KiB."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    return {key: int(fields[key].split()[0]) for key in ("VmRSS", "VmHWM")}


@contextmanager
def _api_memory_bounded(service: Service) -> Iterator[None]:
    """Asserts that the API process's peak resident memory within the block stays within API_GROWTH of its
    resident memory before it (the peak is reset first: ``echo 5 > /proc/<pid>/clear_refs``)."""
    pid = service.procs["api"].pid
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    before = _memory_kib(pid)["VmRSS"]
    yield
    peak = _memory_kib(pid)["VmHWM"]
    assert (peak - before) * 1024 < API_GROWTH, f"the API's peak RSS grew by {(peak - before) // 1024} MiB"


def _refused(response: httpx.Response, status: int, needle: str) -> dict:
    assert response.status_code == status, response.text[:2000]
    assert response.headers["content-type"].startswith("application/json")
    detail = response.json()["detail"]
    assert needle in detail, detail
    return response.json()


def _post_zip(client: httpx.Client, payload: bytes | io.BufferedReader) -> httpx.Response:
    return client.post("/scenes", files={"file": ("scene.zip", payload, "application/zip")})


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def _validators(api_pid: int) -> list[int]:
    """Running validation processes of an API: its grandchildren (children of its forkserver)."""
    return [grandchild for child in _children(api_pid) for grandchild in _children(child)]


def _alive(pid: int) -> bool:
    try:
        return (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]) != "Z"
    except OSError:
        return False


def _stored_nothing(service: Service, before: list) -> None:
    assert sorted(p.name for p in (service.data_dir / "staging").iterdir()) == []
    assert sorted(p.name for p in (service.data_dir / "scenes").iterdir()) == before


# ------------------------------------------------------------------------------------------------ the zip's end record


def test_the_end_record_reader_agrees_with_zipfile_on_a_zip64_archive(tmp_path: Path):
    """70 000 entries need zip64's records (the classic count is 16 bits); zipfile opens the crafted archive."""
    path = tmp_path / "many.zip"
    _write_empty_entries_zip(path, 70_000)
    with open(path, "rb") as f:
        extent = read_directory_extent(f)
        f.seek(0)
        with zipfile.ZipFile(f) as archive:
            infos = archive.infolist()
    assert len(infos) == 70_000 and infos[-1].filename == f"{69_999:05x}"
    assert extent == DirectoryExtent(70_000, sum(46 + len(i.filename) for i in infos))


def test_the_end_record_reader_finds_the_record_behind_a_comment():
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in ("transforms.json", "images/a.png"):
            archive.writestr(name, b"{}")
        archive.comment = b"an archive comment"
    buffer.seek(0)
    assert read_directory_extent(buffer) == DirectoryExtent(2, 2 * 46 + len("transforms.json") + len("images/a.png"))


def test_a_directory_larger_than_its_declared_entries_is_refused_before_parsing(tmp_path: Path):
    """The classic record says 1 entry, the directory holds 5000: zipfile would parse all of them."""
    path = tmp_path / "liar.zip"
    _write_empty_entries_zip(path, 5000, declared=1, zip64=False)
    settings = Settings(data_dir=tmp_path / "data", max_files=10)
    with open(path, "rb") as f:
        extent = read_directory_extent(f)
    assert extent == DirectoryExtent(1, 5000 * 51)
    with pytest.raises(UploadError) as refused:
        check_directory_extent(extent, settings)
    assert refused.value.status_code == 413 and "central directory is 255000 bytes" in refused.value.detail


def test_no_end_record_is_a_422():
    with pytest.raises(UploadError) as refused:
        read_directory_extent(io.BytesIO(b"PK\x03\x04" + bytes(100)))
    assert refused.value.status_code == 422 and "no end-of-central-directory record" in refused.value.detail


# ------------------------------------------------------------------------------------------------ crafted uploads


def test_a_zip_of_a_million_empty_entries_is_refused_from_its_end_record(service, client, million_entry_zip):
    before = sorted(p.name for p in (service.data_dir / "scenes").iterdir())
    with _api_memory_bounded(service), open(million_entry_zip, "rb") as payload:
        response = _post_zip(client, payload)
    _refused(response, 413, "declares 1000000 entries in its end-of-central-directory record")
    _stored_nothing(service, before)


def test_a_200_mb_transforms_json_in_a_zip_is_refused_before_it_is_extracted(service, client):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive, archive.open("transforms.json", "w") as f:
        f.write(b'{"frames": [')
        for _ in range(200):
            f.write(b" " * (BIG_JSON_BYTES // 200))
        f.write(b"]}")
    with _api_memory_bounded(service):
        response = _post_zip(client, buffer.getvalue())
    _refused(response, 413, "transforms.json is 200000014 bytes; the limit is 67108864")


def test_a_200_mb_transforms_json_form_part_is_refused_before_it_is_parsed(service, client, tmp_path: Path):
    sparse = tmp_path / "transforms.json"
    with open(sparse, "wb") as f:  # a hole: 200 MB that occupy no disk
        f.truncate(BIG_JSON_BYTES)
    with _api_memory_bounded(service), open(sparse, "rb") as part:
        response = client.post("/scenes", files=[("files", ("transforms.json", part, "application/json"))])
    _refused(response, 413, f"transforms.json is {BIG_JSON_BYTES} bytes")


def test_many_small_form_parts_are_spooled_to_disk_not_memory(service, client, room_files):
    """2000 parts of 60 kB (120 MB): Starlette kept every part under 1 MiB in memory; they go to one file on
    disk as they stream in, and the scene (valid parts plus the extra ones) is then validated as usual."""
    parts = [("files", (name, data, "application/octet-stream")) for name, data in room_files.items()]
    parts += [("files", (f"extra/{i:04d}.ply", bytes(60_000), "application/octet-stream")) for i in range(2000)]
    with _api_memory_bounded(service):
        response = client.post("/scenes", files=parts)
    assert response.status_code == 201, response.text[:2000]
    assert response.json()["size_bytes"] >= 2000 * 60_000
    assert client.delete(f"/scenes/{response.json()['id']}").status_code == 204


def test_a_png_named_ply_is_checked_by_its_content(service, client, room_files):
    """The prior replaced by a PNG declaring 50 000 x 50 000: refused by its header, not by the PLY reader."""
    with _api_memory_bounded(service):
        response = _post_zip(client, _zip({**room_files, "prior.ply": _png_header_only(50_000, 50_000)}))
    _refused(response, 422, "prior.ply: declared image size 50000x50000 (2500000000 pixels) exceeds the limit")


def test_a_decompression_bomb_is_refused_by_its_header(service, client, room_files):
    """A 1-bit PNG of 20 000 x 20 000 zeros: about 40 kB, 1.2 GB as RGB."""
    bomb = _bomb_png(20_000)
    assert len(bomb) < 100_000
    frame = next(name for name in room_files if name.startswith("images/"))
    with _api_memory_bounded(service):
        response = _post_zip(client, _zip({**room_files, frame: bomb}))
    _refused(response, 422, f"{frame}: declared image size 20000x20000")


def test_images_past_the_scene_pixel_limit_are_refused(service, client, room_files):
    """Each image is small; with a 200 x 200 PNG (named .ply, counted by its content) they pass 40 000 pixels."""
    extra = {"extra/wide.ply": _png(200, 200)}
    with _api_memory_bounded(service):
        response = _post_zip(client, _zip({**room_files, **extra}))
    _refused(response, 413, "VOXNERF_MAX_SCENE_PIXELS")


def test_a_valid_upload_is_validated_outside_the_api_process(service, client, room_files):
    """The scene is accepted, and torch (which the scene checks import) was never loaded by the API process."""
    response = _post_zip(client, _zip(room_files))
    assert response.status_code == 201, response.text
    assert response.json()["summary"]["frames"] == 7
    maps = Path(f"/proc/{service.procs['api'].pid}/maps").read_text()
    assert "libtorch" not in maps
    assert client.delete(f"/scenes/{response.json()['id']}").status_code == 204


def test_memory_hungry_validation_costs_a_413_while_the_api_answers(service, client, room_files):
    """A transforms.json of 12 million empty lists (36 MB, ~1 GB parsed) exhausts the validation process's
    512 MiB. While it is validated, GET /scenes answers and a second upload gets 429 with Retry-After."""
    hostile = _zip({**room_files, "transforms.json": b"[" + b"[]," * EMPTY_LISTS + b"[]]"})
    api_pid = service.procs["api"].pid
    outcome: dict[str, httpx.Response] = {}
    uploader = threading.Thread(target=lambda: outcome.update(upload=_post_zip(client, hostile)))
    with _api_memory_bounded(service), service.client() as other:
        uploader.start()
        validators = wait_for(lambda: _validators(api_pid), 120, "the upload's validation process", 0.005)
        listing = other.get("/scenes")
        second = _post_zip(other, _zip(room_files))
        validating_throughout = all(_alive(pid) for pid in validators)
        uploader.join(300)
    assert listing.status_code == 200 and isinstance(listing.json(), list)
    _refused(second, 429, "VOXNERF_MAX_CONCURRENT_UPLOADS")
    assert second.headers["Retry-After"].isdigit()
    assert validating_throughout, "the validation ended before the other requests were answered"
    _refused(outcome["upload"], 413, "VOXNERF_UPLOAD_VALIDATION_MEMORY_BYTES")


# ------------------------------------------------------------------------------------------------ the child's limits


def _staged_hostile_scene(root: Path, room_files: dict[str, bytes], empty_lists: int) -> StagedUpload:
    scene = root / "staging" / "scene"
    for name, data in {**room_files, "transforms.json": b"[" + b"[]," * empty_lists + b"[]]"}.items():
        (scene / name).parent.mkdir(parents=True, exist_ok=True)
        (scene / name).write_bytes(data)
    return StagedUpload(scene, None)


def test_a_validation_past_its_time_limit_is_killed(tmp_path: Path, room_files):
    settings = Settings(data_dir=tmp_path / "data", upload_validation_timeout_s=0.5)
    upload = _staged_hostile_scene(tmp_path, room_files, EMPTY_LISTS)
    with pytest.raises(UploadError) as refused:
        validate_in_child(upload, settings)
    assert refused.value.status_code == 422
    assert "took longer than 0.5 s (VOXNERF_UPLOAD_VALIDATION_TIMEOUT_S)" in refused.value.detail


def test_a_validation_process_killed_by_a_signal_is_a_422(tmp_path: Path, room_files):
    import multiprocessing

    settings = Settings(data_dir=tmp_path / "data")
    upload = _staged_hostile_scene(tmp_path, room_files, EMPTY_LISTS)
    caught: dict[str, UploadError] = {}

    def validate() -> None:
        try:
            validate_in_child(upload, settings)
        except UploadError as err:
            caught["error"] = err

    thread = threading.Thread(target=validate)
    thread.start()
    child = wait_for(multiprocessing.active_children, 120, "the validation process", 0.005)[0]
    os.kill(child.pid, signal.SIGKILL)
    thread.join(120)
    assert caught["error"].status_code == 422
    assert "validation process was killed by SIGKILL" in caught["error"].detail
    assert json.dumps(caught["error"].detail)  # a plain one-line string
