"""Scoped tokens (issue #44, item 3): named tokens with scopes, the principal of each request, who made and who
cancelled each scene and job, per-token queue limits, and a service whose only tokens are named ones.

Real parts: uvicorn serving the API with a train and a render worker (the filesystem broker) for the scope and
ownership rules; an API without workers for the queue limits (jobs must stay queued); the app over httpx's ASGI
transport where a remote client address is needed (as in test_closed_by_default.py).
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import sqlite3
import stat

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_fixtures import Service, start_service, upload_scene, wait_for, wait_until_final, zip_scene
from sqlalchemy import inspect
from synthetic_fixtures import make_micro_scene

from app.core import db, jobstore, outputs, tokens
from app.core.db import session_scope
from app.core.models import JobRow
from app.core.settings import Settings
from app.main import create_app
from app.origin_guard import UnsafeBindError, check_bind

ADMIN_TOKEN = "tokens-legacy-admin"  # VOXNERF_API_TOKEN: principal "admin"
LONG_JOB = {"max_iters": 100_000, "compile": False}
TRAIN_TIMEOUT_S = 300


def _as(service: Service, token: str | None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.Client(base_url=service.base_url, headers=headers, timeout=60, trust_env=False)


def _make_token(service: Service, name: str, scope: str, **fields) -> str:
    with service.client() as admin:
        response = admin.post("/tokens", json={"name": name, "scope": scope, **fields})
    assert response.status_code == 201, response.text
    return response.json()["token"]


@pytest.fixture(scope="module")
def micro_room(tmp_path_factory):
    return make_micro_scene(tmp_path_factory, "tokens-room")


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("tokens") / "service", token=ADMIN_TOKEN)
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def named(service) -> dict[str, str]:
    """``{name: token}``: a reader, two writers and a named admin."""
    scopes = {"reader": "read", "alice": "write", "bob": "write", "root": "admin"}
    return {name: _make_token(service, name, scope) for name, scope in scopes.items()}


@pytest.fixture(scope="module")
def alices_scene(service, named, micro_room) -> dict:
    with _as(service, named["alice"]) as alice:
        return upload_scene(alice, micro_room)


def _wait_running(service: Service, client: httpx.Client, job_id: str) -> dict:
    return wait_for(lambda: (j := client.get(f"/jobs/{job_id}").json())["state"] == "running" and j["iteration"] > 0
                    and j, TRAIN_TIMEOUT_S, f"job {job_id} to run")


# ------------------------------------------------------------------------------------------------ scopes


def test_a_read_token_reads_but_every_write_is_refused(service, named, alices_scene, micro_room):
    scene_id = alices_scene["id"]
    with _as(service, named["alice"]) as alice:
        job = alice.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 2, "compile": False})
    assert job.status_code == 202, job.text
    job_id = job.json()["id"]
    with _as(service, named["reader"]) as reader:
        assert reader.get("/scenes").status_code == 200
        assert reader.get(f"/scenes/{scene_id}").json()["created_by"] == "alice"
        assert reader.get(f"/jobs/{job_id}").status_code == 200
        assert "database" in reader.get("/healthz").json()  # any valid token gets the health details
        refused = {
            "upload": reader.post("/scenes", files={"file": ("r.zip", zip_scene(micro_room), "application/zip")}),
            "train": reader.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 2}),
            "render": reader.post("/render", json={"job_id": job_id, "transform_matrix": np.eye(4).tolist()}),
            "delete scene": reader.delete(f"/scenes/{scene_id}"),
            "delete job": reader.delete(f"/jobs/{job_id}"),
            "cancel": reader.post(f"/jobs/{job_id}/cancel"),
            "video": reader.post(f"/jobs/{job_id}/videos", json={"path": "orbit", "frames": 2}),
        }
        tokens_route = reader.get("/tokens")
    for what, response in refused.items():
        assert response.status_code == 403, (what, response.text)
        assert "needs scope write; token 'reader' has scope read" in response.json()["detail"], what
    assert tokens_route.status_code == 403 and "needs scope admin" in tokens_route.json()["detail"]
    with service.client() as admin:
        assert len(admin.get("/scenes").json()) == 1  # the refused upload stored nothing
        assert len(admin.get("/jobs").json()) == 1
        wait_until_final(service, admin, f"/jobs/{job_id}", TRAIN_TIMEOUT_S)


def test_write_tokens_train_and_may_cancel_or_delete_only_their_own_work(service, named, alices_scene):
    """Alice uploads and trains; Bob may train on her scene but neither cancel nor delete her work; a named admin
    cancels her job; Alice deletes her own finished job."""
    scene_id = alices_scene["id"]
    assert alices_scene["created_by"] == "alice"
    with _as(service, named["alice"]) as alice, _as(service, named["bob"]) as bob, \
            _as(service, named["root"]) as root:
        job = alice.post(f"/scenes/{scene_id}/jobs", json=LONG_JOB).json()
        assert job["created_by"] == "alice" and job["cancelled_by"] is None
        _wait_running(service, alice, job["id"])  # a real worker trains it

        for response in (bob.post(f"/jobs/{job['id']}/cancel"), bob.delete(f"/scenes/{scene_id}")):
            assert response.status_code == 403, response.text
            assert "was made by 'alice'; token 'bob' (scope write) may cancel or delete only its own work" in (
                response.json()["detail"])
        assert alice.get(f"/jobs/{job['id']}").json()["cancel_requested"] is False

        bobs = bob.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 2, "compile": False})
        assert bobs.status_code == 202 and bobs.json()["created_by"] == "bob"  # training on another's scene is fine

        cancelled = root.post(f"/jobs/{job['id']}/cancel")
        assert cancelled.status_code == 202 and cancelled.json()["cancelled_by"] == "root"
        final = wait_until_final(service, alice, f"/jobs/{job['id']}", 120)
        assert final["state"] == "cancelled" and final["cancelled_by"] == "root" and final["created_by"] == "alice"
        assert bob.post(f"/jobs/{job['id']}/cancel").status_code == 403  # still not his, cancelled or not

        assert bob.delete(f"/jobs/{job['id']}").status_code == 403
        assert alice.get(f"/jobs/{job['id']}").status_code == 200
        assert alice.delete(f"/jobs/{job['id']}").status_code == 204
        assert alice.get(f"/jobs/{job['id']}").status_code == 404
        wait_until_final(service, bob, f"/jobs/{bobs.json()['id']}", TRAIN_TIMEOUT_S)
        assert bob.delete(f"/jobs/{bobs.json()['id']}").status_code == 204  # his own

        listed = {j["id"]: j["created_by"] for j in alice.get("/jobs").json()}
        assert bobs.json()["id"] not in listed and set(listed.values()) <= {"alice"}


def test_the_legacy_token_is_principal_admin_and_acts_on_everyones_work(service, named, alices_scene, micro_room):
    with _as(service, named["alice"]) as alice:
        extra = upload_scene(alice, micro_room)
    with service.client() as admin:
        mine = upload_scene(admin, micro_room)
        assert mine["created_by"] == "admin"
        assert admin.delete(f"/scenes/{extra['id']}").status_code == 204  # alice's, deleted by the admin
        assert admin.delete(f"/scenes/{mine['id']}").status_code == 204


def test_an_upload_session_belongs_to_the_token_that_opened_it(service, named, micro_room):
    """Bob can neither read, add to, complete nor delete Alice's upload session (the session stays as it was); an
    admin can read it; Alice completes it into her own scene. A session opened before sessions had owners is the
    admin's."""
    data = zip_scene(micro_room)
    sha = hashlib.sha256(data).hexdigest()
    with _as(service, named["alice"]) as alice, _as(service, named["bob"]) as bob, \
            _as(service, named["root"]) as root:
        opened = alice.post("/uploads", json={"filename": "room.zip", "total_bytes": len(data)})
        assert opened.status_code == 201 and opened.json()["created_by"] == "alice"
        upload_id = opened.json()["id"]
        scenes_before = {s["id"] for s in root.get("/scenes").json()}
        refused = {
            "read": bob.get(f"/uploads/{upload_id}"),
            "part": bob.put(f"/uploads/{upload_id}/parts/0", content=data, headers={"X-Content-SHA256": sha}),
            "complete": bob.post(f"/uploads/{upload_id}/complete"),
            "delete": bob.delete(f"/uploads/{upload_id}"),
        }
        for what, response in refused.items():
            assert response.status_code == 403, (what, response.text)
            assert response.json()["detail"] == (
                f"upload session {upload_id} was made by 'alice'; token 'bob' (scope write) may read, send parts "
                "to, complete or delete only its own work (scope admin acts on all)"), what
        seen = root.get(f"/uploads/{upload_id}")
        assert seen.status_code == 200 and seen.json()["received_parts"] == []  # bob's part was not kept
        assert bob.get("/uploads/" + "0" * 32).status_code == 404  # no session: 404, owner or not

        assert alice.put(f"/uploads/{upload_id}/parts/0", content=data,
                         headers={"X-Content-SHA256": sha}).status_code == 201
        scene = alice.post(f"/uploads/{upload_id}/complete")
        assert scene.status_code == 201, scene.text
        assert scene.json()["created_by"] == "alice" and scene.json()["id"] not in scenes_before

        legacy = root.post("/uploads", json={"filename": "old.zip", "total_bytes": 10}).json()["id"]
        session_file = service.data_dir / "upload-sessions" / legacy / "session.json"
        old = json.loads(session_file.read_text())
        session_file.write_text(json.dumps({k: v for k, v in old.items() if k != "created_by"}))
        assert bob.get(f"/uploads/{legacy}").status_code == 403
        assert "made by no token (made before tokens existed)" in bob.delete(f"/uploads/{legacy}").json()["detail"]
        assert root.get(f"/uploads/{legacy}").json()["created_by"] is None
        assert root.delete(f"/uploads/{legacy}").status_code == 204


def test_a_revoked_token_is_refused_at_once_and_its_name_is_never_given_again(service, named):
    temporary = _make_token(service, "temporary", "write")
    with _as(service, temporary) as client, _as(service, named["root"]) as root:
        assert client.get("/jobs").status_code == 200
        assert root.delete("/tokens/temporary").status_code == 204
        refused = client.get("/jobs")
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        assert "revoked" in refused.json()["detail"]
        listed = {t["name"]: t for t in root.get("/tokens").json()}
        assert listed["temporary"]["revoked_at"] is not None and listed["temporary"]["last_used_at"] is not None
        assert all("token" not in t and "webhook_secret" not in t for t in listed.values())
        again = root.post("/tokens", json={"name": "temporary", "scope": "read"})
        assert again.status_code == 409 and "never reused" in again.json()["detail"]
        assert root.delete("/tokens/nobody").status_code == 404
        for bad in ({"name": "admin", "scope": "read"}, {"name": "Has Space", "scope": "read"},
                    {"name": "ok", "scope": "root"}, {"name": "ok", "scope": "read", "max_queued": 0}):
            assert root.post("/tokens", json=bad).status_code == 422, bad
    with _as(service, "vxn_" + "A" * 43) as forged, _as(service, "wrong") as wrong:
        assert forged.get("/jobs").status_code == 401 and wrong.get("/jobs").status_code == 401


def test_the_database_and_the_logs_hold_no_plaintext_token(service, named):
    with _as(service, named["alice"]) as alice:  # used, so last_used_at was written
        assert alice.get("/scenes").status_code == 200
    stored = b"".join(path.read_bytes() for path in service.data_dir.glob("voxnerf.sqlite*"))
    assert hashlib.sha256(named["alice"].encode()).hexdigest().encode() in stored  # the right file was read
    logs = service.logs()
    for name, token in named.items():
        secret_part = token.removeprefix(tokens.TOKEN_PREFIX)
        assert token.startswith("vxn_") and len(secret_part) == 43
        assert secret_part.encode() not in stored, f"{name}'s token is in the database"
        assert secret_part not in logs, f"{name}'s token is in a log"


# ------------------------------------------------------------------------------------------------ queue limits


@pytest.fixture(scope="module")
def queue_only(tmp_path_factory):
    """An API without workers (jobs stay queued), two queued jobs per token by default."""
    svc = start_service(tmp_path_factory.mktemp("tokens-queue") / "service", token=ADMIN_TOKEN, workers=False,
                        settings={"VOXNERF_MAX_QUEUED_PER_TOKEN": "2", "VOXNERF_MAX_QUEUED_JOBS": "6"})
    yield svc
    svc.stop()


def test_a_tokens_queue_limit_refuses_it_while_another_token_still_queues(queue_only, micro_room):
    one = _make_token(queue_only, "one", "write", max_queued=1)
    two = _make_token(queue_only, "two", "write")
    with _as(queue_only, one) as first, _as(queue_only, two) as second, queue_only.client() as admin:
        scene_id = upload_scene(first, micro_room)["id"]
        submit = {"max_iters": 2}
        assert first.post(f"/scenes/{scene_id}/jobs", json=submit).status_code == 202
        refused = first.post(f"/scenes/{scene_id}/jobs", json=submit)
        assert refused.status_code == 429
        assert "1 jobs of token 'one' are queued already (its limit is 1: set for this token with --max-queued)" in (
            refused.json()["detail"])
        assert [second.post(f"/scenes/{scene_id}/jobs", json=submit).status_code for _ in range(3)] == [202, 202, 429]
        detail = second.post(f"/scenes/{scene_id}/jobs", json=submit).json()["detail"]
        assert "token 'two'" in detail and "VOXNERF_MAX_QUEUED_PER_TOKEN" in detail
        assert admin.post(f"/scenes/{scene_id}/jobs", json=submit).status_code == 202  # the admin's own count
        owners = sorted(j["created_by"] for j in admin.get("/jobs").json())
        assert owners == ["admin", "one", "two", "two"]  # the refused jobs left no row
        queued_by_one = next(j for j in admin.get("/jobs").json() if j["created_by"] == "one")
        assert first.post(f"/jobs/{queued_by_one['id']}/cancel").status_code == 202  # room again for "one"
        assert first.post(f"/scenes/{scene_id}/jobs", json=submit).status_code == 202


def test_output_jobs_have_the_per_token_limit_too(tmp_path):
    """As test_job_limits.py does for the service-wide limit: the app in process, a job marked succeeded."""
    settings = _settings(tmp_path, api_token=ADMIN_TOKEN, max_queued_per_token=1, max_output_pixels=10**9)
    with TestClient(create_app(settings)) as client:
        jobstore.add_scene(settings, "c" * 32, "room", {"frames": 1}, 10)
        one, two = (tokens.create_token(settings, name, "write").token for name in ("one", "two"))
        trained = client.post(f"/scenes/{'c' * 32}/jobs", json={"max_iters": 5}, headers=_bearer(ADMIN_TOKEN))
        job_id = trained.json()["id"]
        with session_scope(settings) as session:
            session.get(JobRow, job_id).state = "succeeded"
        video = {"path": "orbit", "frames": 4, "width": 16, "height": 12}
        assert client.post(f"/jobs/{job_id}/videos", json=video, headers=_bearer(one)).status_code == 202
        refused = client.post(f"/jobs/{job_id}/exports", json={"kind": "mesh"}, headers=_bearer(one))
        assert refused.status_code == 429, refused.text
        assert "1 outputs of token 'one' are queued already" in refused.json()["detail"]
        assert "VOXNERF_MAX_QUEUED_PER_TOKEN" in refused.json()["detail"]
        made = client.post(f"/jobs/{job_id}/exports", json={"kind": "mesh"}, headers=_bearer(two))
        assert made.status_code == 202 and made.json()["created_by"] == "two"
    assert sorted(row.created_by for row in outputs.OUTPUTS.newest(settings)) == ["one", "two"]


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


# ------------------------------------------------------------------------------------------------ named tokens alone


def _settings(tmp_path, **overrides) -> Settings:
    values = {"data_dir": tmp_path / "data", "device": "cpu", "sweep_interval_s": 3600.0, "health_timeout_s": 0.2}
    return Settings(_env_file=None, **{**values, **overrides})


def test_a_named_token_makes_a_tokenless_service_need_tokens_and_serve_remote_clients(tmp_path):
    settings = _settings(tmp_path)
    app = create_app(settings)

    async def ask(client_host: str, token: str | None = None) -> int:
        transport = httpx.ASGITransport(app=app, client=(client_host, 40000))
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1", headers=headers) as client:
            return (await client.get("/jobs")).status_code

    assert asyncio.run(ask("127.0.0.1")) == 200  # tokenless: loopback clients are principal "local"
    assert asyncio.run(ask("203.0.113.5")) == 403
    with pytest.raises(UnsafeBindError):
        check_bind("0.0.0.0", settings)
    made = tokens.create_token(settings, "ci", "read")
    assert asyncio.run(ask("127.0.0.1")) == 401  # now the service has a token, loopback included
    assert asyncio.run(ask("203.0.113.5")) == 401
    assert asyncio.run(ask("203.0.113.5", made.token)) == 200
    check_bind("0.0.0.0", settings)
    tokens.revoke_token(settings, "ci")
    assert asyncio.run(ask("203.0.113.5", made.token)) == 403  # tokenless again: remote clients refused
    assert asyncio.run(ask("127.0.0.1")) == 200


def test_the_principal_of_each_kind_of_request(tmp_path):
    settings = _settings(tmp_path, api_token="legacy", max_queued_per_token=7)
    made = tokens.create_token(settings, "writer", "write", max_queued=3)
    assert tokens.resolve(settings, "Bearer legacy") == tokens.Principal("admin", "admin")
    assert tokens.resolve(settings, f"bearer {made.token}") == tokens.Principal("writer", "write", 3)
    assert tokens.resolve(settings, None) is None and tokens.resolve(settings, "Bearer vxn_unknown") is None
    assert tokens.resolve(settings, f"Basic {made.token}") is None
    assert tokens.resolve(_settings(tmp_path / "other"), None) == tokens.Principal("local", "admin")
    assert tokens.queue_quota(settings, tokens.Principal("writer", "write", 3)).limit == 3
    assert tokens.queue_quota(settings, tokens.Principal("admin", "admin")).limit == 7
    rules = {("GET", "/jobs"): "read", ("HEAD", "/jobs/x/report"): "read", ("POST", "/render"): "write",
             ("DELETE", "/scenes/x"): "write", ("GET", "/tokens"): "admin", ("DELETE", "/tokens/ci"): "admin",
             ("GET", "/tokensx"): "read"}
    assert {request: tokens.required_scope(*request) for request in rules} == rules


def test_last_used_is_written_at_most_once_a_minute(tmp_path, monkeypatch):
    settings = _settings(tmp_path)
    made = tokens.create_token(settings, "user", "read")
    clock = [1_000_000.0]
    monkeypatch.setattr(tokens.time, "time", lambda: clock[0])
    used = lambda: next(t.last_used_at for t in tokens.list_tokens(settings) if t.name == "user")  # noqa: E731
    tokens.resolve(settings, f"Bearer {made.token}")
    assert used() == clock[0]
    clock[0] += 59
    tokens.resolve(settings, f"Bearer {made.token}")
    assert used() == 1_000_000.0
    clock[0] += 1
    tokens.resolve(settings, f"Bearer {made.token}")
    assert used() == 1_000_060.0


# ------------------------------------------------------------------------------------------------ webhook secrets


def test_webhook_secrets_per_principal(tmp_path):
    settings = _settings(tmp_path, api_token="legacy")
    made = tokens.create_token(settings, "hooks", "write")
    assert tokens.webhook_secret(settings, "hooks") == bytes.fromhex(made.webhook_secret)
    assert tokens.show_secret(settings, "hooks") == made.webhook_secret
    assert tokens.webhook_secret(settings, "admin") == hmac.new(b"legacy", b"voxnerf-webhook", "sha256").digest()
    local = tokens.webhook_secret(settings, "local")
    path = settings.data_dir / "webhook_secret"
    assert len(local) == 32 and path.read_bytes() == local and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert tokens.webhook_secret(settings, "local") == local  # made once
    assert not list(settings.data_dir.glob(".webhook_secret-*"))  # no temporary file left
    with pytest.raises(tokens.TokenError, match="no token named 'nobody'"):
        tokens.webhook_secret(settings, "nobody")
    with pytest.raises(tokens.TokenError, match="no VOXNERF_API_TOKEN"):
        tokens.webhook_secret(_settings(tmp_path / "tokenless"), "admin")


# ------------------------------------------------------------------------------------------------ older databases


def test_a_database_from_before_tokens_gains_the_table_and_the_columns(tmp_path):
    """Its rows read as made by no one: only an admin may cancel or delete them."""
    settings = _settings(tmp_path)
    jobstore.add_scene(settings, "c" * 32, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, "c" * 32, {"max_iters": 5})
    with sqlite3.connect(settings.data_dir / "voxnerf.sqlite") as conn:
        conn.execute("DROP TABLE tokens")
        for table in ("scenes", "jobs", "outputs", "imports"):
            conn.execute(f"ALTER TABLE {table} DROP COLUMN created_by")
        for table in ("jobs", "outputs", "imports"):
            conn.execute(f"ALTER TABLE {table} DROP COLUMN cancelled_by")
    db._engines.clear()  # a new process opens the old database
    engine = db.get_engine(settings)
    found = inspect(engine)
    columns = {table: {c["name"] for c in found.get_columns(table)} for table in found.get_table_names()}
    assert "token_sha256" in columns["tokens"] and "created_by" in columns["scenes"]
    assert all({"created_by", "cancelled_by"} <= columns[table] for table in ("jobs", "outputs", "imports"))
    old = jobstore.JOBS.get(settings, job.id)
    assert old.created_by is None
    assert tokens.may_act_on(tokens.Principal("admin", "admin"), old.created_by)
    assert not tokens.may_act_on(tokens.Principal("alice", "write"), old.created_by)
    assert tokens.create_token(settings, "after", "read").name == "after"
