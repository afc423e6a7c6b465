"""The object store (app/core/storage.py) against moto's S3 server running as a real process on loopback.

Unit tests: round trip of a directory, the completion marker (an unfinished upload is invisible, a damaged
one refused), missing scenes, cache refresh rules for runs, uploads during training. End to end: an API and
workers with DIFFERENT data directories, so that only the store carries scenes and runs between them.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from pydantic import SecretStr
from service_fixtures import Service, first_pose, free_port, start_redis, start_service, wait_for, zip_scene

from app.core import storage
from app.core.disk_space import directory_bytes
from app.core.settings import Settings
from voxnerf.inference.render import CHECKPOINT, load_model, render

KEY, SECRET = "test-key", "test-secret"


@pytest.fixture(scope="module")
def moto_endpoint(tmp_path_factory) -> Iterator[str]:
    """moto's S3 server on a free loopback port, for the whole module."""
    port = free_port()
    log = tmp_path_factory.mktemp("moto") / "moto.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    endpoint = f"http://127.0.0.1:{port}"
    try:

        def up() -> bool:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                return True
            except OSError:
                return proc.poll() is not None  # died: stop waiting, the assert below reports it

        wait_for(up, 30, "moto_server to listen")
        assert proc.poll() is None, log.read_text()
        yield endpoint
    finally:
        proc.terminate()
        proc.wait(10)


def _settings(data_dir: Path, endpoint: str, storage_url: str) -> Settings:
    """Settings of one 'machine' (its own data_dir) on the moto store at ``storage_url``."""
    return Settings(
        data_dir=data_dir,
        storage_url=storage_url,
        storage_endpoint_url=endpoint,
        storage_key=SecretStr(KEY),
        storage_secret=SecretStr(SECRET),
    )


@pytest.fixture
def store_url() -> str:
    return f"s3://voxnerf-test/{uuid.uuid4().hex}"


@pytest.fixture
def machines(tmp_path, moto_endpoint, store_url) -> tuple[Settings, Settings]:
    """Two 'machines' sharing one store; the bucket is created by check_store as at worker start-up."""
    a = _settings(tmp_path / "a", moto_endpoint, store_url)
    b = _settings(tmp_path / "b", moto_endpoint, store_url)
    for settings in (a, b):
        settings.make_dirs()
    storage.check_store(a)
    return a, b


def _tree(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in root.rglob("*")
        if p.is_file() and p.name != storage.LOCAL_GENERATION
    }


def _fill(root: Path, seed: int) -> dict[str, bytes]:
    rng = np.random.default_rng(seed)
    files = {
        "transforms.json": b'{"frames": []}',
        "images/0001.png": rng.bytes(5000),
        "images/sub/0002.png": rng.bytes(17),
        "prior.ply": b"",
    }
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    return files


def test_round_trip_and_old_generations_removed(machines, tmp_path):
    a, b = machines
    store = storage.open_store(a)
    src = tmp_path / "src"
    files = _fill(src, 0)
    first = storage.put_dir(store, src, "scenes/s1")
    assert storage.local_generation(src) == first
    (src / "images/0001.png").write_bytes(b"changed")
    files["images/0001.png"] = b"changed"
    second = storage.put_dir(store, src, "scenes/s1")
    assert second != first

    dst = b.scenes_dir / "s1"
    assert storage.fetch_dir(store, "scenes/s1", dst, b.staging_dir) == second
    assert _tree(dst) == files
    assert storage.local_generation(dst) == second
    store.fs.invalidate_cache()
    listed = {p.rsplit("/", 1)[-1] for p in store.fs.ls(store.path("scenes/s1"), detail=False)}
    assert listed == {second, storage.MARKER}  # the older generation is gone, the marker stays
    assert not list(b.staging_dir.iterdir())  # no temporary download left behind


def test_upload_without_marker_is_invisible(machines, tmp_path):
    a, b = machines
    store = storage.open_store(a)
    # An upload that died before its marker: its files are in the store, the marker is not.
    store.fs.pipe_file(store.path("scenes/half/abc/transforms.json"), b"{}")
    assert storage.read_marker(store, "scenes/half") is None
    with pytest.raises(storage.StorageError, match=r"scenes/half: not in the store \(no current.json"):
        storage.fetch_dir(store, "scenes/half", b.scenes_dir / "half", b.staging_dir)
    assert not (b.scenes_dir / "half").exists()


def test_damaged_upload_refused_and_cache_untouched(machines, tmp_path):
    a, b = machines
    store = storage.open_store(a)
    src = tmp_path / "src"
    _fill(src, 1)
    generation = storage.put_dir(store, src, "runs/j1")
    store.fs.pipe_file(store.path(f"runs/j1/{generation}/images/0001.png"), b"short")
    with pytest.raises(storage.StorageError, match=r"images/0001.png: 5 bytes, the marker says 5000"):
        storage.fetch_dir(store, "runs/j1", b.runs_dir / "j1", b.staging_dir)
    store.fs.rm_file(store.path(f"runs/j1/{generation}/prior.ply"))
    with pytest.raises(storage.StorageError, match="a file the marker lists is missing"):
        storage.fetch_dir(store, "runs/j1", b.runs_dir / "j1", b.staging_dir)
    store.fs.pipe_file(store.path(f"runs/j1/{storage.MARKER}"), b'{"generation": "x", "files": {"../e": 1}}')
    with pytest.raises(storage.StorageError, match=r"current.json: damaged marker .*'\.\./e'"):
        storage.read_marker(store, "runs/j1")
    assert not (b.runs_dir / "j1").exists()


def test_scene_publish_fetch_delete(machines, tmp_path):
    a, b = machines
    files = _fill(a.scenes_dir / "scene1", 2)
    storage.publish_scene(a, "scene1")
    local = storage.ensure_scene(b, "scene1")
    assert local == b.scenes_dir / "scene1" and _tree(local) == files
    storage.delete_scene(a, "scene1")
    assert storage.read_marker(storage.open_store(a), "scenes/scene1") is None
    assert storage.ensure_scene(b, "scene1") == local  # a cached scene stays usable on its machine
    with pytest.raises(storage.StorageError, match=r"s3://voxnerf-test/.*/scenes/missing: not in the store"):
        storage.ensure_scene(b, "missing")


def test_without_store_nothing_changes(tmp_path):
    settings = Settings(data_dir=tmp_path)
    assert storage.open_store(settings) is None
    storage.check_store(settings)
    storage.publish_scene(settings, "x")
    storage.delete_scene(settings, "x")
    assert storage.ensure_scene(settings, "x") == settings.scenes_dir / "x"
    assert storage.ensure_run(settings, "j", refresh=False) == settings.runs_dir / "j"
    assert not any(tmp_path.iterdir())


def test_s3_credentials_refused_for_other_protocols(tmp_path):
    settings = Settings(data_dir=tmp_path, storage_url=f"file://{tmp_path}/store", storage_key=SecretStr("k"))
    with pytest.raises(ValueError, match="VOXNERF_STORAGE_KEY apply to s3:// stores only"):
        storage.open_store(settings)


def test_run_refresh_rules(machines):
    """A worker's cache is kept when it holds the store's generation, replaced when another machine
    uploaded since; a render worker fetches only what it lacks."""
    a, b = machines
    run_a = storage.ensure_run(a, "job1")
    assert not run_a.exists()  # nothing uploaded yet: training starts from scratch
    run_a.mkdir(parents=True)
    (run_a / CHECKPOINT).write_bytes(b"iteration-10")
    storage.put_dir(storage.open_store(a), run_a, "runs/job1")

    run_b = storage.ensure_run(b, "job1")  # B resumes A's job
    assert (run_b / CHECKPOINT).read_bytes() == b"iteration-10"
    (run_b / CHECKPOINT).write_bytes(b"iteration-15-not-uploaded")
    storage.ensure_run(b, "job1")  # same generation: B's newer local checkpoint is kept
    assert (run_b / CHECKPOINT).read_bytes() == b"iteration-15-not-uploaded"

    (run_a / CHECKPOINT).write_bytes(b"iteration-20")
    storage.put_dir(storage.open_store(a), run_a, "runs/job1")
    storage.ensure_run(b, "job1", refresh=False)  # rendering: a cached checkpoint is enough
    assert (run_b / CHECKPOINT).read_bytes() == b"iteration-15-not-uploaded"
    storage.ensure_run(b, "job1")  # training: A uploaded since, B takes it
    assert (run_b / CHECKPOINT).read_bytes() == b"iteration-20"
    with pytest.raises(storage.StorageError, match="runs/nojob: not in the store"):
        storage.ensure_run(b, "nojob", refresh=False)


def test_run_publisher_uploads_new_checkpoints_and_the_end(machines):
    a, b = machines
    run = a.runs_dir / "job2"
    run.mkdir(parents=True)
    store = storage.open_store(a)
    with storage.RunPublisher(a, "job2", run) as publisher:
        assert not publisher.upload_if_changed()  # no checkpoint yet
        (run / CHECKPOINT).write_bytes(b"first")
        assert publisher.upload_if_changed()
        assert not publisher.upload_if_changed()  # unchanged
        assert set(storage.read_marker(store, "runs/job2")["files"]) == {CHECKPOINT}
        temp = run / f".{CHECKPOINT}.123.tmp"  # an atomic write in progress is never uploaded
        temp.write_bytes(b"partial")
        os.replace(temp, run / CHECKPOINT)
        (run / "report.json").write_text('{"status": "succeeded"}')
        (run / "eval" / "interpolation").mkdir(parents=True)
        (run / "eval" / "interpolation" / "v.png").write_bytes(b"png")
    marker = storage.read_marker(store, "runs/job2")
    assert marker["files"] == {CHECKPOINT: 7, "report.json": 23, "eval/interpolation/v.png": 3}
    fetched = storage.ensure_run(b, "job2", refresh=False)
    assert _tree(fetched) == _tree(run)


def test_run_publisher_uploads_in_the_background(machines):
    a, _ = machines
    settings = a.model_copy(update={"storage_sync_interval_s": 0.1})
    run = settings.runs_dir / "job3"
    run.mkdir(parents=True)
    store = storage.open_store(settings)
    with storage.RunPublisher(settings, "job3", run):
        (run / CHECKPOINT).write_bytes(b"saved during training")
        wait_for(lambda: storage.read_marker(store, "runs/job3"), 20, "the side thread to upload", 0.05)


# ----- end to end: API and workers on different data directories, joined only by the store and Redis


@pytest.mark.slow
def test_service_with_separate_data_dirs(tmp_path, moto_endpoint, store_url):
    from voxnerf.synthetic import RoomSpec, make_room_scene

    scene_dir = tmp_path / "room"
    spec = RoomSpec(width=64, height=48, n_frames=24, train_every=3, gap_len=6, prior_max_points=20_000)
    make_room_scene(scene_dir, spec)
    redis = start_redis(tmp_path / "redis")
    common = {
        "VOXNERF_STORAGE_URL": store_url,
        "VOXNERF_STORAGE_ENDPOINT_URL": moto_endpoint,
        "VOXNERF_STORAGE_KEY": KEY,
        "VOXNERF_STORAGE_SECRET": SECRET,
        "VOXNERF_STORAGE_SYNC_INTERVAL_S": "0.5",
        # The job store is a database every process reaches (PostgreSQL in production).
        "VOXNERF_DATABASE_URL": f"sqlite:///{tmp_path / 'jobs.sqlite'}",
    }
    api = workers = None
    try:
        api = start_service(tmp_path / "api", broker_url=redis.url, settings=common, workers=False)
        worker_data = tmp_path / "workers" / "data"
        worker_data.mkdir(parents=True)
        worker_env = dict(api.env, VOXNERF_DATA_DIR=str(worker_data))
        workers = Service(tmp_path / "workers", worker_env, api.port, None, "redis")
        workers.start_worker("train")
        workers.start_worker("render")
        api.wait_healthy()
        with api.client() as client:
            response = client.post(
                "/scenes", files={"file": ("room.zip", zip_scene(scene_dir), "application/zip")}
            )
            assert response.status_code == 201, response.text
            scene_id = response.json()["id"]
            response = client.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 5, "compile": False})
            assert response.status_code == 202, response.text
            job_id = response.json()["id"]

            def finished() -> dict | None:
                job = client.get(f"/jobs/{job_id}").json()
                return job if job["state"] in ("succeeded", "failed", "cancelled") else None

            job = wait_for(finished, 300, f"job {job_id} to finish", 0.5)
            assert job["state"] == "succeeded", f"{job}\n{api.logs()}\n{workers.logs()}"
            # The worker trained from its own fetched copy; the API never saw the run.
            assert (worker_data / "scenes" / scene_id / "transforms.json").is_file()
            assert (worker_data / "runs" / job_id / CHECKPOINT).is_file()
            assert not (api.data_dir / "runs" / job_id).exists()
            probe = _settings(tmp_path / "probe", moto_endpoint, store_url)
            store = storage.open_store(probe)
            marker = storage.read_marker(store, f"runs/{job_id}")
            assert {CHECKPOINT, "report.json"} <= set(marker["files"])
            # The API lists and serves the evaluation renders from its own copy, fetched from the store.
            renders = client.get(f"/jobs/{job_id}/renders").json()
            assert renders, f"no evaluation renders\n{api.logs()}"
            for entry in renders:
                worker_png = worker_data / "runs" / job_id / "eval" / entry["split"] / f"{entry['name']}.png"
                assert client.get(entry["url"]).content == worker_png.read_bytes()
            assert (api.data_dir / "runs" / job_id / CHECKPOINT).is_file()
            # Reference: the uploaded model rendered here, in this process.
            pose = first_pose(scene_dir)
            trained = load_model(storage.ensure_run(probe, job_id, refresh=False), "cpu")
            rgb = render(trained, np.asarray(pose), outputs=("rgb",))["rgb"]
            expected = np.round(np.clip(rgb, 0.0, 1.0) * 255.0)

            # A render worker whose cache lacks the run fetches it from the store.
            (worker_data / "runs").rename(worker_data / "runs-evicted")
            response = client.post(
                "/render", json={"job_id": job_id, "transform_matrix": pose, "width": 64, "height": 48}
            )
            assert response.status_code == 200, f"{response.text}\n{workers.logs()}"
            image = iio.imread(response.content)
            assert image.shape == expected.shape == (48, 64, 3)
            assert np.abs(image.astype(np.float64) - expected).max() <= 1.0
            assert (worker_data / "runs" / job_id / CHECKPOINT).is_file()

            assert client.delete(f"/scenes/{scene_id}").status_code == 204
            assert storage.read_marker(store, f"scenes/{scene_id}") is None
    finally:
        for service in (workers, api):
            if service is not None:
                service.stop()
        redis.stop()


def test_a_worker_cache_past_its_size_is_pruned_and_fetched_again(tmp_path, tmp_path_factory, moto_endpoint,
                                                                  store_url):
    """Real workers whose cache may hold 1 byte (``VOXNERF_WORKER_CACHE_BYTES``): after training, the train
    worker removes the scene and the run (the store holds both); a render fetches the run again, and a second
    job on the scene fetches the scene again."""
    from synthetic_fixtures import make_micro_scene

    redis = start_redis(tmp_path / "redis")
    common = {
        "VOXNERF_STORAGE_URL": store_url,
        "VOXNERF_STORAGE_ENDPOINT_URL": moto_endpoint,
        "VOXNERF_STORAGE_KEY": KEY,
        "VOXNERF_STORAGE_SECRET": SECRET,
        "VOXNERF_DATABASE_URL": f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        "OMP_NUM_THREADS": "1",
    }
    api = workers = None
    try:
        api = start_service(tmp_path / "api", broker_url=redis.url, settings=common, workers=False)
        worker_data = tmp_path / "workers" / "data"
        worker_data.mkdir(parents=True)
        workers = Service(tmp_path / "workers", dict(api.env, VOXNERF_DATA_DIR=str(worker_data),
                                                     VOXNERF_WORKER_CACHE_BYTES="1"), api.port, None, "redis")
        workers.start_worker("train")
        workers.start_worker("render")
        api.wait_healthy()
        with api.client() as client:
            archive = zip_scene(make_micro_scene(tmp_path_factory, "cache-scene"))
            scene_id = client.post("/scenes", files={"file": ("room.zip", archive, "application/zip")}).json()["id"]

            def trained() -> dict:
                response = client.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 2, "compile": False})
                assert response.status_code == 202, response.text
                job_id = response.json()["id"]
                job = wait_for(lambda: (j := client.get(f"/jobs/{job_id}").json())["state"] in (
                    "succeeded", "failed", "cancelled") and j, 300, f"job {job_id} to finish", 0.5)
                assert job["state"] == "succeeded", f"{job}\n{workers.logs()}"
                return job

            job = trained()
            wait_for(lambda: not any(any((worker_data / kind).iterdir()) for kind in ("scenes", "runs")), 30,
                     "the train worker to prune its cache")
            assert "worker cache: removed" in (workers.root / "worker-train.log").read_text()
            response = client.post("/render", json={"job_id": job["id"], "transform_matrix": np.eye(4).tolist(),
                                                    "width": 16, "height": 12})
            assert response.status_code == 200, f"{response.text}\n{workers.logs()}"
            trained()  # the scene is fetched again
    finally:
        for service in (workers, api):
            if service is not None:
                service.stop()
        redis.stop()


def test_upload_refused_with_503_when_the_store_is_down(tmp_path):
    """The API keeps no scene the store did not take: no directory, no row, a 503 naming the cause."""
    from app.core import jobstore
    from app.uploads import staging as uploads
    from voxnerf.synthetic import RoomSpec, make_room_scene

    scene_dir = tmp_path / "room"
    make_room_scene(scene_dir, RoomSpec(width=32, height=24, n_frames=8, train_every=2, gap_len=2, n_gaps=1,
                                        prior_max_points=2_000, supersample=1))
    settings = _settings(tmp_path / "api", f"http://127.0.0.1:{free_port()}", "s3://voxnerf-test/down")
    settings = settings.model_copy(
        update={"storage_options": {"config_kwargs": {"retries": {"max_attempts": 1}, "connect_timeout": 2}}}
    )
    parts = [(p.relative_to(scene_dir).as_posix(), p.open("rb")) for p in scene_dir.rglob("*") if p.is_file()]
    try:
        with pytest.raises(uploads.UploadError) as refused:
            uploads.store_parts(settings, "room", [(n, f) for n, f in parts if n != "gt_mesh.ply"])
    finally:
        for _, f in parts:
            f.close()
    assert refused.value.status_code == 503
    assert "could not be copied to the object store" in refused.value.detail
    assert not any(settings.scenes_dir.iterdir())
    assert jobstore.list_scenes(settings) == []


def test_api_start_up_fails_clearly_when_the_store_is_unreachable(tmp_path):
    from fastapi.testclient import TestClient

    from app.main import create_app

    url = f"http://127.0.0.1:{free_port()}"
    settings = _settings(tmp_path / "api", url, "s3://voxnerf-test/unreachable").model_copy(
        update={"storage_options": {"config_kwargs": {"retries": {"max_attempts": 1}, "connect_timeout": 2}}}
    )
    app = create_app(settings)
    expected = r"s3://voxnerf-test/unreachable \(VOXNERF_STORAGE_URL\) cannot be used"
    with pytest.raises(storage.StorageError, match=expected), TestClient(app):
        pass


def test_the_store_names_the_engines_checkpoint():
    """app.core.storage cannot import voxnerf.inference.render (torch) for the name; the two must agree."""
    assert storage.CHECKPOINT == CHECKPOINT


# ------------------------------------------------------------------------------------------------ worker cache


def _publish_scene(a: Settings, scene_id: str, seed: int) -> None:
    _fill(a.scenes_dir / scene_id, seed)
    storage.publish_scene(a, scene_id)


def _used_at(settings: Settings, kind: str, entry_id: str, when: float) -> None:
    """Hold the entry as a task does, then date its last use ``when`` (older entries go first)."""
    with storage.cache_entry_in_use(settings, kind, entry_id):
        pass
    lock = settings.data_dir / storage.CACHE_LOCKS / f"{kind}-{entry_id}.lock"
    os.utime(lock, (when, when))


def test_the_worker_cache_drops_least_recently_used_entries_the_store_holds(machines):
    a, b = machines
    for seed, scene_id in enumerate(("s-old", "s-mid", "s-new")):
        _publish_scene(a, scene_id, seed)
    one = directory_bytes(a.scenes_dir / "s-old") + 64  # each scene's files and its generation record
    b = b.model_copy(update={"worker_cache_bytes": 2 * one})
    for when, scene_id in enumerate(("s-old", "s-mid", "s-new")):
        with storage.cache_entry_in_use(b, storage.SCENES, scene_id):
            storage.ensure_scene(b, scene_id)
        _used_at(b, storage.SCENES, scene_id, 1_000_000 + when)
    assert storage.prune_cache(b) == ["scenes/s-old"]
    assert sorted(p.name for p in b.scenes_dir.iterdir()) == ["s-mid", "s-new"]
    assert storage.prune_cache(b) == []  # it fits now
    with storage.cache_entry_in_use(b, storage.SCENES, "s-old"):  # the store still holds it: fetched again
        assert _tree(storage.ensure_scene(b, "s-old")) == _tree(a.scenes_dir / "s-old")
    assert not list(b.staging_dir.iterdir())


def test_the_worker_cache_keeps_entries_in_use_and_runs_the_store_lacks(machines):
    a, b = machines
    b = b.model_copy(update={"worker_cache_bytes": 1})  # over it with anything: only the rules below keep entries
    _publish_scene(a, "busy", 0)
    with storage.cache_entry_in_use(b, storage.SCENES, "busy"):
        storage.ensure_scene(b, "busy")
        _fill(b.runs_dir / "never-uploaded", 1)  # a run whose upload failed: the cache holds the only copy
        changed = b.runs_dir / "changed"
        _fill(changed, 2)
        storage.put_dir(storage.open_store(b), changed, "runs/changed")
        (changed / "images/0001.png").write_bytes(b"a newer checkpoint, not uploaded yet")
        unpublished = b.runs_dir / "unpublished-output"
        _fill(unpublished, 3)
        storage.put_dir(storage.open_store(b), unpublished, "runs/unpublished-output")
        (unpublished / "outputs" / "o1").mkdir(parents=True)
        (unpublished / "outputs" / "o1" / "video.mp4").write_bytes(b"being rendered")
        uploaded = b.runs_dir / "uploaded"
        _fill(uploaded, 4)
        storage.put_dir(storage.open_store(b), uploaded, "runs/uploaded")
        for when, (kind, entry_id) in enumerate([(storage.SCENES, "busy"), (storage.RUNS, "never-uploaded"),
                                                 (storage.RUNS, "changed"), (storage.RUNS, "unpublished-output"),
                                                 (storage.RUNS, "uploaded")]):
            if entry_id != "busy":
                _used_at(b, kind, entry_id, 1_000_000 + when)
        assert storage.prune_cache(b) == ["runs/uploaded"]  # the held scene, oldest of all, stays
    assert storage.prune_cache(b) == ["scenes/busy"]  # released: now it goes
    assert sorted(p.name for p in b.runs_dir.iterdir()) == ["changed", "never-uploaded", "unpublished-output"]


def test_without_a_store_the_cache_is_never_pruned(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", worker_cache_bytes=1)
    settings.make_dirs()
    _fill(settings.scenes_dir / "s1", 0)
    with storage.cache_entry_in_use(settings, storage.SCENES, "s1"):
        pass
    assert storage.prune_cache(settings) == []
    assert (settings.scenes_dir / "s1").is_dir() and not (settings.data_dir / storage.CACHE_LOCKS).exists()
