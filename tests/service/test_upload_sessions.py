"""Upload sessions (``/uploads``) through a real uvicorn: a part cut off by a dropped connection is resent and the
completed session gives the same scene as a one-request upload; each refusal (bad part hash, wrong size, other
bytes for a received part, missing parts, whole-file hash, expiry, size and session limits) leaves no scene."""

from __future__ import annotations

import hashlib
import os
import socket
import time

import httpx
import pytest
from service_fixtures import start_service, upload_scene, wait_for, zip_scene

PART = 256 * 1024
MAX_SESSIONS = 3
MAX_SESSION_BYTES = 64 * 1024 * 1024


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    service = start_service(
        tmp_path_factory.mktemp("upload-sessions"),
        token="session-token",
        workers=False,
        settings={
            "VOXNERF_UPLOAD_PART_BYTES": str(PART),
            "VOXNERF_MAX_UPLOAD_SESSIONS": str(MAX_SESSIONS),
            "VOXNERF_MAX_UPLOAD_SESSION_BYTES": str(MAX_SESSION_BYTES),
        },
    )
    yield service
    service.stop()


@pytest.fixture(scope="module")
def client(service):
    with service.client() as client:
        yield client


@pytest.fixture(scope="module")
def archive(small_room) -> bytes:
    data = zip_scene(small_room)
    assert len(data) > 3 * PART, "the scene's zip must take several parts"
    return data


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _parts(data: bytes) -> list[bytes]:
    return [data[i:i + PART] for i in range(0, len(data), PART)]


def _create(client: httpx.Client, data: bytes, **extra) -> dict:
    response = client.post("/uploads", json={"filename": "room.zip", "total_bytes": len(data), **extra})
    assert response.status_code == 201, response.text
    return response.json()


def _put(client: httpx.Client, upload_id: str, number: int, data: bytes, sha: str | None = None) -> httpx.Response:
    return client.put(f"/uploads/{upload_id}/parts/{number}", content=data,
                      headers={"X-Content-SHA256": sha or _sha(data)})


def _scene_files(service, scene_id: str) -> dict[str, str]:
    root = service.data_dir / "scenes" / scene_id
    return {p.relative_to(root).as_posix(): _sha(p.read_bytes()) for p in sorted(root.rglob("*")) if p.is_file()}


def _drop_mid_part(service, upload_id: str, number: int, data: bytes) -> None:
    """Send the headers and half the body of a part, then close the connection (a dropped upload)."""
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        head = (f"PUT /uploads/{upload_id}/parts/{number} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                f"Authorization: Bearer {service.token}\r\nX-Content-SHA256: {_sha(data)}\r\n"
                f"Content-Type: application/octet-stream\r\nContent-Length: {len(data)}\r\n\r\n")
        sock.sendall(head.encode() + data[: len(data) // 2])
        time.sleep(0.3)  # the server has begun reading the body


def test_a_part_dropped_mid_way_is_resent_and_the_scene_matches_a_one_request_upload(service, client, archive,
                                                                                         small_room):
    direct = upload_scene(client, small_room)
    session = _create(client, archive, sha256=_sha(archive), name="resumed room")
    assert session["part_bytes"] == PART and session["part_count"] == len(_parts(archive))
    parts = _parts(archive)
    assert _put(client, session["id"], 0, parts[0]).status_code == 201

    _drop_mid_part(service, session["id"], 1, parts[1])
    incoming = service.data_dir / "upload-sessions" / session["id"] / "incoming"
    wait_for(lambda: not any(incoming.iterdir()), 10, "the cut-off part's temporary file to be removed")
    state = client.get(f"/uploads/{session['id']}").json()
    assert state["received_parts"] == [0] and state["received_bytes"] == PART
    assert state["missing_parts"] == len(parts) - 1 and state["expires_at"] > time.time()

    for number in range(len(parts)):  # what a client resuming does: send every part not listed
        if number not in state["received_parts"]:
            response = _put(client, session["id"], number, parts[number])
            assert response.status_code == 201 and response.json()["new"], response.text
    again = _put(client, session["id"], 0, parts[0])  # a part resent with the same bytes is harmless
    assert again.status_code == 200 and not again.json()["new"]

    done = client.post(f"/uploads/{session['id']}/complete")
    assert done.status_code == 201, done.text
    scene = done.json()
    assert scene["name"] == "resumed room" and scene["summary"] == direct["summary"]
    assert _scene_files(service, scene["id"]) == _scene_files(service, direct["id"])
    assert client.get(f"/uploads/{session['id']}").status_code == 404  # completing consumed the session
    assert not (service.data_dir / "upload-sessions" / session["id"]).exists()


def _scene_ids(client: httpx.Client) -> set[str]:
    return {scene["id"] for scene in client.get("/scenes").json()}


def test_each_bad_part_is_refused_and_nothing_becomes_a_scene(service, client, archive):
    before = _scene_ids(client)
    parts = _parts(archive)
    session = _create(client, archive)
    upload_id = session["id"]

    bad_hash = _put(client, upload_id, 0, parts[0], sha=_sha(b"something else"))
    assert bad_hash.status_code == 422 and "X-Content-SHA256" in bad_hash.json()["detail"]
    short = _put(client, upload_id, 0, parts[0][:-1])
    assert short.status_code == 422 and f"{PART} expected" in short.json()["detail"]
    long = _put(client, upload_id, 0, parts[0] + b"x")
    assert long.status_code == 413
    assert _put(client, upload_id, 0, b"not a hash", sha="xyz").status_code == 422
    beyond = _put(client, upload_id, len(parts), b"x")
    assert beyond.status_code == 404 and "parts 0 to" in beyond.json()["detail"]
    assert client.put(f"/uploads/{upload_id}/parts/0", content=parts[0]).status_code == 422  # no hash header

    assert _put(client, upload_id, 0, parts[0]).status_code == 201
    other = bytes(reversed(parts[0]))
    changed = _put(client, upload_id, 0, other)
    assert changed.status_code == 409 and "other bytes" in changed.json()["detail"]

    missing = client.post(f"/uploads/{upload_id}/complete")
    assert missing.status_code == 409, missing.text
    assert f"{len(parts) - 1} of {len(parts)} parts not received" in missing.json()["detail"]
    assert client.get(f"/uploads/{upload_id}").json()["received_parts"] == [0]  # the session is kept
    assert client.delete(f"/uploads/{upload_id}").status_code == 204
    assert client.get(f"/uploads/{upload_id}").status_code == 404
    assert client.delete(f"/uploads/{upload_id}").status_code == 404
    assert _scene_ids(client) == before


def test_a_whole_file_hash_that_differs_removes_the_session(service, client, archive):
    before = _scene_ids(client)
    session = _create(client, archive, sha256=_sha(b"another file"))
    for number, part in enumerate(_parts(archive)):
        assert _put(client, session["id"], number, part).status_code == 201
    response = client.post(f"/uploads/{session['id']}/complete")
    assert response.status_code == 422 and "hashes to" in response.json()["detail"]
    assert client.get(f"/uploads/{session['id']}").status_code == 404
    assert _scene_ids(client) == before
    assert not any((service.data_dir / "staging").iterdir())  # the joined file is gone too


def test_a_file_that_is_no_scene_is_refused_as_post_scenes_refuses_it(client):
    data = os.urandom(PART + 10)
    session = _create(client, data)
    for number, part in enumerate(_parts(data)):
        assert _put(client, session["id"], number, part).status_code == 201
    response = client.post(f"/uploads/{session['id']}/complete")
    direct = client.post("/scenes", files={"file": ("room.zip", data, "application/zip")})
    assert response.status_code == direct.status_code == 422
    assert response.json()["detail"] == direct.json()["detail"]


def test_an_idle_session_expires_and_the_sweeper_removes_it(service, client, archive):
    session = _create(client, archive)
    assert _put(client, session["id"], 0, _parts(archive)[0]).status_code == 201
    path = service.data_dir / "upload-sessions" / session["id"]
    long_ago = time.time() - 2 * 86_400  # idle for longer than the default expiry (a day)
    os.utime(path, (long_ago, long_ago))
    expired = client.get(f"/uploads/{session['id']}")
    assert expired.status_code in (404, 410), expired.text  # 410 until the sweeper (every second here) runs
    if expired.status_code == 410:
        assert "expired" in expired.json()["detail"]
    wait_for(lambda: not path.exists(), 15, "the sweeper to remove the expired session")
    assert client.get(f"/uploads/{session['id']}").status_code == 404
    assert _put(client, session["id"], 1, _parts(archive)[1]).status_code == 404


def test_limits_of_size_and_of_open_sessions(client):
    too_large = client.post("/uploads", json={"filename": "big.zip", "total_bytes": MAX_SESSION_BYTES + 1})
    assert too_large.status_code == 413 and "VOXNERF_MAX_UPLOAD_SESSION_BYTES" in too_large.json()["detail"]
    for body in ({"filename": "a.zip", "total_bytes": 0}, {"filename": "a.zip", "total_bytes": 10, "sha256": "ab"},
                 {"filename": "a.zip", "total_bytes": 10, "splits": "odd"}, {"filename": "", "total_bytes": 10}):
        assert client.post("/uploads", json=body).status_code == 422, body
    opened = [client.post("/uploads", json={"filename": "a.zip", "total_bytes": 10}) for _ in range(MAX_SESSIONS)]
    assert [r.status_code for r in opened] == [201] * MAX_SESSIONS
    refused = client.post("/uploads", json={"filename": "a.zip", "total_bytes": 10})
    assert refused.status_code == 429 and "VOXNERF_MAX_UPLOAD_SESSIONS" in refused.json()["detail"]
    for response in opened:
        assert client.delete(f"/uploads/{response.json()['id']}").status_code == 204
    assert client.post("/uploads", json={"filename": "a.zip", "total_bytes": 10}).status_code == 201


def test_sessions_need_the_token(service):
    with service.client(auth=False) as anonymous:
        assert anonymous.post("/uploads", json={"filename": "a.zip", "total_bytes": 10}).status_code == 401
