"""Hypothesis fuzzing of the REST API through HTTP: hostile uploads, ids and JSON bodies never make a 500.

The app runs in-process (Starlette's TestClient over ASGI, lifespan included) on a temporary ``data_dir``,
with no workers. Every upload starts from a valid 7-frame 32x24 scene and is then mutated: random bytes,
truncated archives, bytes flipped in the central directory, a mutated ``transforms.json`` (wrong types,
missing keys, huge numbers, NaN, deep nesting, non-UTF-8), odd entry names (unicode, absolute, ``..``,
backslashes, very long, deep), duplicate entries, images that are not images or have the wrong size,
wrong content types and missing form fields; the multi-file form gets the same treatment. Ids in every
URL and the JSON bodies of ``POST /scenes/{id}/jobs`` and ``POST /render`` are fuzzed too.

Every response must be 2xx, or 4xx with a JSON ``detail``; a refused upload must leave nothing behind
(no scene directory, no staging entry, no database row). Examples are derandomised, so CI is stable.
"""

from __future__ import annotations

import io
import json
import math
import struct
import warnings
import zipfile
import zlib
from collections.abc import Iterator
from urllib.parse import quote

import imageio.v3 as iio
import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from app.core import jobstore
from app.core.settings import Settings
from app.main import create_app
from voxnerf.synthetic import RoomSpec, make_room_scene

MiB = 1024 * 1024
FUZZ = settings(
    max_examples=100,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

# ------------------------------------------------------------------------------------------------ fixtures


class Api:
    """The app under test and what the fuzzers start from."""

    def __init__(self, client: TestClient, config: Settings, files: dict[str, bytes], meta: dict,
                 scene_id: str, job_id: str) -> None:
        self.client = client
        self.settings = config
        self.files = files  # the valid scene: path inside the scene -> bytes
        self.meta = meta  # its transforms.json
        self.scene_id = scene_id  # a stored scene (it has a queued job, so it is never deleted)
        self.job_id = job_id  # a queued job (no worker runs here)

    def __repr__(self) -> str:  # hypothesis prints the fixture with every failing example
        return f"Api(scene_id={self.scene_id!r}, job_id={self.job_id!r})"


@pytest.fixture(scope="module")
def api(tmp_path_factory) -> Iterator[Api]:
    root = tmp_path_factory.mktemp("fuzz")
    scene_dir = root / "room"
    make_room_scene(
        scene_dir,
        RoomSpec(width=32, height=24, n_frames=8, train_every=2, n_gaps=0, gap_len=0, prior_max_points=2000,
                 supersample=1),
    )
    meta = json.loads((scene_dir / "transforms.json").read_text())
    meta.pop("voxnerf_synthetic")  # keep transforms.json to the keys the loader reads
    files = {
        p.relative_to(scene_dir).as_posix(): p.read_bytes()
        for p in sorted(scene_dir.rglob("*"))
        if p.is_file() and p.name not in ("gt_mesh.ply", "transforms.json")
    }
    files["transforms.json"] = json.dumps(meta).encode()
    config = Settings(
        data_dir=root / "data",
        device="cpu",
        max_upload_bytes=4 * MiB,
        max_scene_bytes=8 * MiB,
        max_files=64,
        max_image_pixels=1_000_000,
        sweep_interval_s=3600,
        health_timeout_s=0.2,
        render_timeout_s=1,
    )
    with TestClient(create_app(config), raise_server_exceptions=False) as client:
        stored = client.post("/scenes", files={"file": ("room.zip", _zip(files), "application/zip")})
        assert stored.status_code == 201, stored.text
        scene_id = stored.json()["id"]
        job = client.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 5, "compile": False})
        assert job.status_code == 202, job.text
        yield Api(client, config, files, meta, scene_id, job.json()["id"])


# ------------------------------------------------------------------------------------------------ helpers


def _zip(entries: dict[str, bytes] | list[tuple[str, bytes]], top: str | None = "room") -> bytes:
    """A deflated zip of ``entries`` (duplicates allowed in a list), under the folder ``top`` when given.

    Names are stored as given, NUL bytes included (``zipfile.ZipInfo`` would cut them off).
    """
    items = entries.items() if isinstance(entries, dict) else entries
    out = io.BytesIO()
    with warnings.catch_warnings(), zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        warnings.simplefilter("ignore", UserWarning)  # "Duplicate name": wanted here
        for name, data in items:
            info = zipfile.ZipInfo("x")
            info.filename = f"{top}/{name}" if top else name
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, data)
    return out.getvalue()


def _checked(response) -> None:
    """2xx, or 4xx with a non-empty JSON ``detail``; never 5xx."""
    where = f"{response.request.method} {response.request.url}"
    assert response.status_code < 500, f"{where} -> {response.status_code}: {response.text[:2000]}"
    if response.status_code >= 400:
        assert response.headers.get("content-type", "").startswith("application/json"), where
        assert response.json().get("detail"), f"{where} -> {response.status_code} without a detail"


def _stored(config: Settings) -> tuple[set[str], list[str], set[str]]:
    """What an upload can leave behind: scene directories, staging entries, database rows."""
    scenes = {p.name for p in config.scenes_dir.iterdir()}
    staging = sorted(p.name for p in config.staging_dir.iterdir())
    rows = {row.id for row in jobstore.list_scenes(config)}
    return scenes, staging, rows


def _upload(api: Api, **request) -> int:
    """POST /scenes; checks the response, then that a refusal stored nothing and an acceptance stored one
    scene (deleted again). Returns the status code."""
    before = _stored(api.settings)
    assert before[1] == [], "staging was not empty before the upload"
    response = api.client.post("/scenes", **request)
    _checked(response)
    after = _stored(api.settings)
    if response.status_code == 201:
        new = response.json()["id"]
        assert after == (before[0] | {new}, [], before[2] | {new}), "an accepted upload stored too much"
        assert api.client.delete(f"/scenes/{new}").status_code == 204
        after = _stored(api.settings)
    assert after == before, f"upload answered {response.status_code} but left something behind"
    return response.status_code


def _post_zip(api: Api, payload: bytes, filename: str = "scene.zip", content_type: str = "application/zip"):
    return _upload(api, files={"file": (filename, payload, content_type)})


def _png(width: int, height: int, channels: int = 3, dtype=np.uint8) -> bytes:
    pixels = np.zeros((height, width, channels) if channels > 1 else (height, width), dtype)
    return iio.imwrite("<bytes>", pixels, extension=".png")


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG signature and a valid IHDR chunk declaring ``width x height``; no pixel data."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(
        ">I", zlib.crc32(b"IHDR" + ihdr)
    )


def _npy_header(shape: tuple[int, ...]) -> bytes:
    """A version 1.0 ``.npy`` header declaring a float32 array of ``shape`` (no data)."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f4", "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def _paths(value, prefix: tuple = ()) -> list[tuple]:
    """Every key path into a JSON value (dict keys and list indices), the value itself first."""
    found = [prefix]
    if isinstance(value, dict):
        for key, item in value.items():
            found += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            found += _paths(item, (*prefix, index))
    return found


def _mutate(meta: dict, path: tuple, op: str, value, key: str) -> dict:
    """A deep copy of ``meta`` with ``value`` set at ``path`` (``op == "set"``), the item there removed
    (``"delete"``), or ``value`` added under ``key`` to the object at ``path`` (``"add"``)."""
    meta = json.loads(json.dumps(meta))
    if not path:
        return value if op == "set" else {**meta, key: value} if op == "add" else {}
    parent = meta
    for step in path[:-1]:
        parent = parent[step]
    if op == "set":
        parent[path[-1]] = value
    elif op == "add" and isinstance(parent[path[-1]], dict):
        parent[path[-1]][key] = value
    else:
        del parent[path[-1]]
    return meta


# ------------------------------------------------------------------------------------------------ strategies

NAME_CHARS = st.characters(blacklist_categories=("Cs",))  # anything a zip can hold but lone surrogates
JSON_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.sampled_from([10**400, -(10**400), 2**63, 2**64 + 1, -1, 0, 1e308, -1e308, 5e-324, 1e-300]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=24),  # lone surrogates included: JSON text carries them as \udXXX escapes
    st.sampled_from(["../../etc/passwd", "/etc/passwd", "images", ".", "", "C:\\x.png", "PINHOLE", "OPENCV"]),
)
JSON_VALUES = st.recursive(
    JSON_SCALARS,
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
ENTRY_NAMES = st.one_of(
    st.text(NAME_CHARS, max_size=40),
    st.text(st.sampled_from("ab./\\:é漢\x00 "), min_size=1, max_size=30),
    st.sampled_from(
        [
            "../evil.png", "/abs.png", "a\\b.png", "C:x.png", "a/../../b.json", "transforms.json",
            "images/frame-000000.png", "x" * 300 + ".png", "dir/", "./transforms.json", "__MACOSX/._x.png",
            ".DS_Store", "é/ü.png", "images//frame-000000.png", "images", "transforms.json/x.json",
            "/".join(["d" * 200] * 30) + "/f.png", "/".join(["d"] * 3000) + "/f.png", "con.png", "a.PNG",
            "prior.ply/x.ply", " .png", "images/frame-000000.png/",
        ]
    ),
)
# (offset, size, telling values) of the fields of a central directory record
_SIZES = [0, 1, 2**31, 2**32 - 1]
CENTRAL_DIRECTORY_FIELDS = [
    (4, 2, [0x0314, 0xFFFF]),  # made by (3: unix, so the file type bits count)
    (8, 2, [1, 8, 0x41, 0x800, 0xFFFF]),  # flags: encrypted, data descriptor, strong encryption, UTF-8
    (10, 2, [0, 8, 9, 12, 14, 93, 99]),  # method: stored, deflate, deflate64, bzip2, lzma, zstd, AES
    (16, 4, [0, 2**32 - 1]),  # CRC-32
    (20, 4, _SIZES),  # compressed size
    (24, 4, _SIZES),  # uncompressed size
    (28, 2, [0, 1, 0xFFFF]),  # name length
    (30, 2, [0, 4, 0xFFFF]),  # extra field length
    (38, 4, [0o120777 << 16, 0o040755 << 16, 0o010644 << 16, 0o020644 << 16]),  # link, dir, fifo, char dev
    (42, 4, [0, 1, 2**32 - 1]),  # offset of the local header
]
CONTENT_TYPES = st.one_of(
    st.sampled_from(
        ["application/zip", "application/octet-stream", "text/plain", "image/png", "", "multipart/form-data",
         "application/json; charset=utf-8", "application/x-zip-compressed"]
    ),
    st.text(st.characters(min_codepoint=0x21, max_codepoint=0x7E), max_size=30),
)


@st.composite
def bad_image_bytes(draw, original: bytes) -> bytes:
    kind = draw(
        st.sampled_from(["empty", "random", "truncated", "size", "header", "gray16", "rgba", "text", "jpeg"])
    )
    if kind == "empty":
        return b""
    if kind == "random":
        return draw(st.binary(max_size=200))
    if kind == "truncated":
        return original[: draw(st.integers(0, len(original) - 1))]
    if kind == "size":
        return _png(draw(st.integers(1, 40)), draw(st.integers(1, 40)))
    if kind == "header":
        return _png_header_only(draw(st.integers(0, 2**31 - 1)), draw(st.integers(0, 2**31 - 1)))
    if kind == "gray16":
        return _png(32, 24, 1, np.uint16)
    if kind == "rgba":
        return _png(32, 24, 4)
    if kind == "jpeg":
        return iio.imwrite("<bytes>", np.zeros((24, 32, 3), np.uint8), extension=".jpg")
    return b"this is not an image"


# ------------------------------------------------------------------------------------------------ uploads


@FUZZ
@given(data=st.data())
def test_fuzzed_archives_never_500(api: Api, data) -> None:
    """Random bytes, truncated archives, and bytes overwritten anywhere (the central directory included)."""
    good = _zip(api.files)
    kind = data.draw(st.sampled_from(["random", "truncated", "flip", "flip_directory", "field", "field"]))
    if kind == "random":
        payload = data.draw(st.binary(max_size=4096))
    elif kind == "truncated":
        payload = good[: data.draw(st.integers(0, len(good) - 1))]
    elif kind == "field":  # one field of central directory records: flags, method, sizes, lengths, offset
        payload = good
        for _ in range(data.draw(st.integers(1, 3))):
            offset, size, values = data.draw(st.sampled_from(CENTRAL_DIRECTORY_FIELDS))
            value = data.draw(st.sampled_from(values) | st.integers(0, 2 ** (8 * size) - 1))
            record = data.draw(st.integers(0, len(api.files) - 1))
            payload = _set_field(payload, offset, size, value, slice(record, record + 1))
    else:
        directory = struct.unpack("<I", good[good.rfind(b"PK\x05\x06") + 16:][:4])[0]
        low = directory if kind == "flip_directory" else 0
        payload = bytearray(good)
        for _ in range(data.draw(st.integers(1, 8))):
            payload[data.draw(st.integers(low, len(good) - 1))] = data.draw(st.integers(0, 255))
        payload = bytes(payload)
    _post_zip(api, payload)


def _set_field(archive: bytes, offset: int, size: int, value: int, records: slice) -> bytes:
    """``archive`` with one field of the chosen central directory records overwritten by ``value``."""
    payload = bytearray(archive)
    starts = [i for i in range(len(archive)) if archive.startswith(b"PK\x01\x02", i)]
    for start in starts[records]:
        payload[start + offset: start + offset + size] = value.to_bytes(size, "little")
    return bytes(payload)


@pytest.mark.parametrize("records", [slice(None), slice(-1, None)], ids=["every_entry", "last_entry"])
@pytest.mark.parametrize(
    ("offset", "size", "value"),
    [(offset, size, value) for offset, size, values in CENTRAL_DIRECTORY_FIELDS for value in values],
)
def test_every_telling_central_directory_value_never_500(api: Api, offset, size, value, records) -> None:
    """Each telling value of each field, in every record or in the last (largest) one: blind fuzzing finds
    e.g. "bzip2 claimed for deflated data" too rarely to rely on it."""
    _post_zip(api, _set_field(_zip(api.files), offset, size, value, records))


@FUZZ
@given(data=st.data())
def test_fuzzed_transforms_json_never_500(api: Api, data) -> None:
    """Keys set to hostile values or removed (1 to 3 at a time), or the whole file replaced by odd bytes."""
    kind = data.draw(st.sampled_from(["mutate", "mutate", "mutate", "raw"]))
    if kind == "mutate":
        meta = api.meta
        for _ in range(data.draw(st.integers(1, 3))):
            path = data.draw(st.sampled_from(_paths(meta)))
            op = data.draw(st.sampled_from(["set", "set", "delete", "add"]))
            key = data.draw(st.text(max_size=70) | st.sampled_from(["..", "../../x", "a/b", "train"]))
            meta = _mutate(meta, path, op, data.draw(JSON_VALUES), key)
        text = json.dumps(meta)  # NaN and Infinity are written as JavaScript literals
        raw = text.encode(data.draw(st.sampled_from(["utf-8", "utf-8", "utf-16", "utf-8-sig"])))
    else:
        depth = data.draw(st.integers(500, 200_000))
        raw = data.draw(
            st.sampled_from(
                [
                    b"[" * depth + b"]" * depth,
                    b'{"frames": ' + b"[" * depth + b"]" * depth + b"}",
                    b"\xff\xfe\x00garbage",
                    json.dumps(api.meta).encode().replace(b"PINHOLE", b"PIN\xffHOLE"),
                    b"",
                    b"null",
                    b'{"frames": []}',
                    b"1" * 5000,
                    b'{"fl_x": ' + b"9" * 5000 + b"}",
                ]
            )
        )
    _post_zip(api, _zip({**api.files, "transforms.json": raw}))


@FUZZ
@given(
    extra=st.lists(st.tuples(ENTRY_NAMES, st.binary(max_size=64)), min_size=1, max_size=3),
    top=st.sampled_from([None, "room"]),
)
def test_odd_entry_names_never_500(api: Api, extra: list[tuple[str, bytes]], top: str | None) -> None:
    """Entries with odd names added to a valid scene (escaping, long, deep, unicode, clashing)."""
    assume(all(name for name, _ in extra) or top)  # a zip entry needs a name
    _post_zip(api, _zip([*api.files.items(), *extra], top=top))


@FUZZ
@given(data=st.data())
def test_bad_members_and_duplicates_never_500(api: Api, data) -> None:
    """An image, depth map or prior replaced by bad bytes, entries duplicated or dropped."""
    files = dict(api.files)
    target = data.draw(st.sampled_from(sorted(files)))
    files[target] = data.draw(bad_image_bytes(files[target]))
    entries = list(files.items())
    for name in data.draw(st.lists(st.sampled_from(sorted(files)), max_size=2)):
        entries.append((name, data.draw(st.sampled_from([files[name], b"", b"other bytes"]))))
    dropped = set(data.draw(st.lists(st.sampled_from(sorted(files)), max_size=2)))
    _post_zip(api, _zip([(n, b) for n, b in entries if n not in dropped]))


@FUZZ
@given(
    filename=st.one_of(st.none(), st.text(NAME_CHARS, max_size=40)),
    content_type=CONTENT_TYPES,
    name=st.one_of(st.none(), st.text(NAME_CHARS, max_size=300)),
)
def test_form_filenames_content_types_and_names_never_500(api: Api, filename, content_type, name) -> None:
    """The valid zip under odd part filenames, content types and display names."""
    status = _upload(
        api,
        files={"file": (filename, _zip(api.files), content_type)},
        data={} if name is None else {"name": name},
    )
    # a part without a (non-empty) filename is a plain form field, not a file: "no scene"; the rest passes
    assert status == (201 if filename else 422)


@FUZZ
@given(
    fields=st.lists(
        st.tuples(
            st.sampled_from(["file", "files", "name", "x", "", "file[]"]),
            st.one_of(st.text(NAME_CHARS, max_size=20), st.binary(max_size=64)),
            st.booleans(),  # sent as a file part (True) or a plain field
        ),
        max_size=10,
    ),
    content_type=st.sampled_from(
        [None, "multipart/form-data", "multipart/form-data; boundary=", "application/json", "text/plain",
         "application/x-www-form-urlencoded", "multipart/form-data; boundary=xyz; charset=nope"]
    ),
    raw=st.binary(max_size=256),
)
def test_malformed_forms_never_500(api: Api, fields, content_type, raw: bytes) -> None:
    """Missing, repeated and mistyped form fields, and raw bodies under any content type."""
    if content_type is None:
        files = [(key, ("part.bin", value if isinstance(value, bytes) else value.encode(), "application/zip"))
                 for key, value, as_file in fields if as_file]
        data = {key: value for key, value, as_file in fields if not as_file and isinstance(value, str)}
        if not files and not data:
            data = {"name": "nothing"}
        status = _upload(api, files=files or None, data=data)
    else:
        status = _upload(api, content=raw, headers={"Content-Type": content_type})
    assert status != 201


def _multipart(parts: list[tuple[str, str | None, bytes]], boundary: bytes) -> bytes:
    """A multipart/form-data body of ``(field, filename or None, bytes)`` parts."""
    body = b""
    for field, filename, data in parts:
        disposition = f'form-data; name="{field}"' + ("" if filename is None else f'; filename="{filename}"')
        body += b"--" + boundary + b"\r\nContent-Disposition: " + disposition.encode() + b"\r\n"
        body += b"Content-Type: application/zip\r\n\r\n" + data + b"\r\n"
    return body + b"--" + boundary + b"--\r\n"


@FUZZ
@given(data=st.data())
def test_mutated_multipart_bodies_never_500(api: Api, data) -> None:
    """A well-formed upload body, then bytes overwritten in its part headers or its end, or cut short."""
    boundary = b"fuzz-boundary-0123"
    body = bytearray(_multipart([("name", None, b"room"), ("file", "room.zip", _zip(api.files))], boundary))
    if data.draw(st.booleans()):
        del body[data.draw(st.integers(0, len(body) - 1)):]
    for _ in range(data.draw(st.integers(0, 6))):
        position = data.draw(st.integers(0, 300) | st.integers(len(body) - 60, len(body) - 1))
        if 0 <= position < len(body):
            body[position] = data.draw(st.sampled_from(b'\r\n-";=\x00\xff') | st.integers(0, 255))
    declared = data.draw(st.sampled_from([boundary.decode(), "other", ""]))
    _upload(api, content=bytes(body), headers={"Content-Type": f"multipart/form-data; boundary={declared}"})


@FUZZ
@given(data=st.data())
def test_fuzzed_multi_file_uploads_never_500(api: Api, data) -> None:
    """The scene sent as parts, with parts renamed, replaced, duplicated or dropped."""
    parts = [(name, body) for name, body in api.files.items()]
    for _ in range(data.draw(st.integers(1, 3))):
        index = data.draw(st.integers(0, len(parts) - 1))
        name, body = parts[index]
        change = data.draw(st.sampled_from(["rename", "replace", "duplicate", "drop", "add"]))
        if change == "rename":
            parts[index] = (data.draw(ENTRY_NAMES), body)
        elif change == "replace":
            parts[index] = (name, data.draw(bad_image_bytes(body)))
        elif change == "duplicate":
            parts.append((name, body))
        elif change == "drop" and len(parts) > 1:
            parts.pop(index)
        else:
            parts.append((data.draw(ENTRY_NAMES), data.draw(st.binary(max_size=64))))
    content_type = data.draw(CONTENT_TYPES)
    _upload(api, files=[("files", (name, body, content_type)) for name, body in parts])


def test_both_zip_and_files_is_refused(api: Api) -> None:
    status = _upload(
        api,
        files=[("file", ("a.zip", _zip(api.files), "application/zip")),
               ("files", ("transforms.json", api.files["transforms.json"], "application/json"))],
    )
    assert status == 422


def _meta_with(api: Api, **changes) -> bytes:
    return _zip({**api.files, "transforms.json": json.dumps({**api.meta, **changes}).encode()})


@pytest.mark.parametrize(
    ("case", "needle"),
    [
        ("bzip2_claimed", "corrupt compressed data"),  # bz2 raises OSError, which was a 500
        ("long_path", "longer than 1024 bytes"),  # ENAMETOOLONG while extracting was a 500
        ("deep_path", "deeper than 32 folders"),
        ("surrogate_path", "file not found: \\udcff.ply"),  # an unencodable detail was a 500
        ("split_traversal", "split name '../../x'"),  # eval renders went to eval/<split>/: outside the run
        ("split_surrogate", "split name"),
        ("huge_npy", "declared image size 100000x100000"),  # np.load allocated the declared array first
        ("npy_version_9", "cannot read .npy header"),
    ],
)
def test_hostile_uploads_found_while_fuzzing_are_refused(api: Api, case: str, needle: str) -> None:
    good = _zip(api.files)
    interpolation = api.meta["eval_splits"]["interpolation"]
    payload = {
        "bzip2_claimed": lambda: _set_field(good, 10, 2, zipfile.ZIP_BZIP2, slice(None)),
        "long_path": lambda: _zip({**api.files, "/".join(["d" * 200] * 30) + "/f.png": b"x"}),
        "deep_path": lambda: _zip({**api.files, "/".join(["d"] * 300) + "/f.png": b"x"}),
        "surrogate_path": lambda: _meta_with(api, prior_file_path="\udcff.ply"),
        "split_traversal": lambda: _meta_with(api, eval_splits={"../../x": interpolation}),
        "split_surrogate": lambda: _meta_with(api, eval_splits={"\ud800": interpolation}),
        "huge_npy": lambda: _zip({**api.files, "depth/big.npy": _npy_header((100_000, 100_000)) + bytes(64)}),
        "npy_version_9": lambda: _zip({**api.files, "d.npy": b"\x93NUMPY\x09\x00" + bytes(64)}),
    }[case]()
    before = _stored(api.settings)
    response = api.client.post("/scenes", files={"file": ("s.zip", payload, "application/zip")})
    assert response.status_code == 422, response.text
    assert needle in response.json()["detail"]
    assert _stored(api.settings) == before


@pytest.mark.parametrize(
    "options", [{"eval_every_s": math.inf}, {"eval_at": [math.nan]}, {"max_seconds": math.nan}]
)
def test_non_finite_job_options_are_refused(api: Api, options: dict) -> None:
    """``eval_every_s: Infinity`` was accepted and stored as null, so the worker failed the job later."""
    content = json.dumps({"max_iters": 5, **options}).encode()
    response = api.client.post(
        f"/scenes/{api.scene_id}/jobs", content=content, headers={"Content-Type": "application/json"}
    )
    assert response.status_code == 422, response.text
    assert next(iter(options)) in json.dumps(response.json()["detail"])


# ------------------------------------------------------------------------------------------------ ids in URLs

IDS = st.one_of(
    st.text(NAME_CHARS, max_size=40),
    st.from_regex(r"[0-9a-fA-F]{30,34}", fullmatch=True),
    st.sampled_from(["..", ".", "%2e%2e", "../../etc/passwd", "0" * 32 + "/..", "\x00" * 32, "0" * 10_000,
                     "0" * 31 + "\n", " " + "0" * 31]),
)


@FUZZ
@given(
    ident=IDS,
    safe=st.sampled_from(["", "/", "/.%"]),
    route=st.sampled_from(
        [
            ("GET", "/scenes/{}"),
            ("DELETE", "/scenes/{}"),
            ("POST", "/scenes/{}/jobs"),
            ("GET", "/jobs/{}"),
            ("POST", "/jobs/{}/cancel"),
            ("GET", "/jobs/{}/renders"),
            ("GET", "/jobs/{}/renders/test/x.png"),
            ("GET", "/jobs/JOB/renders/{}/x.png"),
            ("GET", "/jobs/JOB/renders/test/{}"),
            ("GET", "/jobs?scene_id={}"),
            ("GET", "/jobs?limit={}"),
        ]
    ),
)
def test_fuzzed_ids_in_urls_never_500(api: Api, ident: str, safe: str, route: tuple[str, str]) -> None:
    method, template = route
    url = template.replace("JOB", api.job_id).format(quote(ident, safe=safe))
    body = {"json": {"max_iters": 5, "compile": False}} if method == "POST" else {}
    response = api.client.request(method, url, **body)
    _checked(response)
    # only a listing or the dashboard (where the client folded a '..' away) may answer 2xx
    assert response.status_code >= 400 or response.request.url.path in ("/", "/scenes", "/jobs"), url


@pytest.mark.parametrize("segments", [("test", "a" * 5000 + ".png"), ("a" * 5000, "x.png")])
def test_overlong_render_path_segments_are_404(api: Api, segments: tuple[str, str]) -> None:
    split, filename = segments
    response = api.client.get(f"/jobs/{api.job_id}/renders/{split}/{filename}")
    _checked(response)
    assert response.status_code == 404


# ------------------------------------------------------------------------------------------------ JSON bodies

JOB_KEYS = ["preset", "sampler", "max_seconds", "max_iters", "depth_loss", "downscale", "seed", "compile",
            "eval_at", "eval_every_s", "lr", "device", "unknown"]
RENDER_KEYS = ["width", "height", "fl_x", "fl_y", "cx", "cy", "format", "outputs", "extra"]
MATRICES = st.one_of(
    JSON_VALUES,
    st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=4, max_size=4), min_size=3,
             max_size=5),
    st.just(np.eye(4).tolist()),
)


def _post_json(api: Api, url: str, body, raw: bool) -> None:
    if raw:
        response = api.client.post(url, content=body, headers={"Content-Type": "application/json"})
    else:
        content = json.dumps(body).encode()  # may hold NaN / Infinity literals, as hostile clients send
        response = api.client.post(url, content=content, headers={"Content-Type": "application/json"})
    _checked(response)


@FUZZ
@given(
    body=st.one_of(
        JSON_VALUES,
        st.dictionaries(st.sampled_from(JOB_KEYS), JSON_VALUES, max_size=5),
        st.fixed_dictionaries({"max_iters": st.integers(1, 100)},
                              optional={k: JSON_SCALARS for k in JOB_KEYS if k != "max_iters"}),
    ),
    raw=st.one_of(
        st.none(), st.binary(max_size=128), st.sampled_from([b"[" * 100_000, b'{"max_iters": 1e999}'])
    ),
)
def test_fuzzed_job_options_never_500(api: Api, body, raw: bytes | None) -> None:
    url = f"/scenes/{api.scene_id}/jobs"
    _post_json(api, url, raw if raw is not None else body, raw is not None)


@FUZZ
@given(
    job=st.one_of(st.just("JOB"), IDS, JSON_SCALARS),
    matrix=MATRICES,
    extra=st.dictionaries(st.sampled_from(RENDER_KEYS), JSON_VALUES, max_size=4),
    raw=st.one_of(st.none(), st.binary(max_size=128)),
)
def test_fuzzed_render_requests_never_500(api: Api, job, matrix, extra: dict, raw: bytes | None) -> None:
    body = {"job_id": api.job_id if job == "JOB" else job, "transform_matrix": matrix, **extra}
    _post_json(api, "/render", raw if raw is not None else body, raw is not None)
