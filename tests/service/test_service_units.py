"""The service's building blocks without servers: archive-name safety, render requests and their encoding,
the atomic filesystem broker, and the job store's fencing and stale-job recovery."""

from __future__ import annotations

import multiprocessing
import os
import socket
import time

import imageio.v3 as iio
import numpy as np
import pytest
from kombu import Connection, Exchange, Queue

from app.core import jobstore
from app.core.celery_app import create_celery
from app.core.db import session_scope
from app.core.dispatch import requeue_stale
from app.core.models import JobRow
from app.core.render_request import RenderRequest
from app.core.settings import Settings
from app.uploads.staging import TRANSFORMS, UploadError, safe_relpath
from voxnerf.cameras.rays import Intrinsics
from voxnerf.data.image_io import decode_exr, srgb_to_linear
from voxnerf.inference.encoding import encode_outputs as encode_render
from voxnerf.training.records import EvalRecord, ProgressEvent


@pytest.mark.parametrize(
    "name",
    [
        "../x.png",
        "a/../../x.png",
        "/etc/x.png",
        "C:/x.png",
        "c:x.png",
        "a\\b.png",
        "a\x00.png",
        "",
        "./",
        "a/" + "x" * 256 + ".png",
    ],
)
def test_unsafe_archive_names_are_refused(name):
    with pytest.raises(UploadError) as info:
        safe_relpath(name)
    assert info.value.status_code == 422 and info.value.detail.startswith("entry ")


def test_safe_archive_names_are_normalised():
    assert str(safe_relpath("room/./images//a.png")) == "room/images/a.png"
    assert str(safe_relpath("transforms.json")) == "transforms.json"


DEFAULT = Intrinsics(fl_x=50.0, fl_y=52.0, cx=32.0, cy=24.0, width=64, height=48)


def _request(**fields) -> RenderRequest:
    return RenderRequest(job_id="a" * 32, transform_matrix=np.eye(4).tolist(), **fields)


def test_render_intrinsics_default_scaled_and_explicit():
    assert _request().intrinsics(DEFAULT) == DEFAULT
    half = _request(width=32, height=24).intrinsics(DEFAULT)
    assert half == Intrinsics(25.0, 26.0, 16.0, 12.0, 32, 24)
    stretched = _request(width=128, height=48, fl_x=10.0, cy=5.0).intrinsics(DEFAULT)
    assert stretched == Intrinsics(10.0, 52.0, 64.0, 5.0, 128, 48)


def test_render_request_defaults_and_pose_cleanup():
    assert _request().outputs == ["rgb"] and _request(format="exr").outputs == ["rgb", "depth", "opacity"]
    assert _request(format="exr", outputs=["depth", "depth"]).outputs == ["depth"]
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = rot * (1 + 1e-3)  # slightly off: re-orthonormalised, like the engine does for scenes
    pose[:3, 3] = [1, 2, 3]
    cleaned = np.asarray(RenderRequest(job_id="a" * 32, transform_matrix=pose.tolist()).transform_matrix)
    np.testing.assert_allclose(cleaned[:3, :3], rot, atol=1e-9)
    np.testing.assert_allclose(cleaned[:3, 3], [1, 2, 3])


def test_encode_render_png_and_exr_round_trip():
    rng = np.random.default_rng(0)
    images = {
        "rgb": rng.random((6, 8, 3), dtype=np.float32),
        "depth": rng.uniform(0.5, 4.0, (6, 8)).astype(np.float32),
        "opacity": rng.random((6, 8), dtype=np.float32),
    }
    rgb = iio.imread(encode_render(images, "png", ["rgb"], 0.001))
    assert rgb.dtype == np.uint8 and rgb.shape == (6, 8, 3)
    np.testing.assert_allclose(rgb / 255.0, images["rgb"], atol=0.5 / 255 + 1e-6)
    depth = iio.imread(encode_render(images, "png", ["depth"], 0.001))
    assert depth.dtype == np.uint16 and depth.shape == (6, 8)
    np.testing.assert_allclose(depth * 0.001, images["depth"], atol=0.0005 + 1e-6)
    alpha = iio.imread(encode_render(images, "png", ["opacity"], 0.001))
    assert alpha.shape == (6, 8) and alpha.dtype == np.uint8
    channels = decode_exr(encode_render(images, "exr", ["rgb", "depth", "opacity"], 0.001))
    assert sorted(channels) == ["A", "B", "G", "R", "Z"]
    np.testing.assert_array_equal(np.stack([channels[c] for c in "RGB"], -1), srgb_to_linear(images["rgb"]))
    np.testing.assert_array_equal(channels["Z"], images["depth"])
    np.testing.assert_array_equal(channels["A"], images["opacity"])
    assert sorted(decode_exr(encode_render(images, "exr", ["depth"], 0.001))) == ["Z"]


def _broker(folder) -> Connection:
    options = {
        "data_folder_in": str(folder / "q"),
        "data_folder_out": str(folder / "q"),
        "control_folder": str(folder / "c"),
        "claimed_folder": str(folder / "claimed"),
        "polling_interval": 0.01,
    }
    return Connection("filesystem://", transport="app.core.broker:Transport", transport_options=options)


def _broker_folders(folder) -> None:
    """The queue, control and claimed folders that :func:`_broker` names, under ``folder``."""
    for name in ("q", "c", "claimed"):
        (folder / name).mkdir()


def _consume(folder, out):
    got = []
    with _broker(folder) as conn:
        queue = conn.SimpleQueue("jobs")
        idle_since = time.monotonic()
        while time.monotonic() - idle_since < 1.0:
            try:
                message = queue.get(timeout=0.05)
            except queue.Empty:
                continue
            got.append(message.payload["n"])
            message.ack()
            idle_since = time.monotonic()
        queue.close()
    out.put(got)


def test_filesystem_broker_delivers_each_message_once_to_competing_consumers(tmp_path):
    _broker_folders(tmp_path)
    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    consumers = [context.Process(target=_consume, args=(tmp_path, out)) for _ in range(2)]
    for proc in consumers:
        proc.start()
    with _broker(tmp_path) as conn:
        queue = conn.SimpleQueue("jobs")
        for n in range(200):
            queue.put({"n": n})
        queue.close()
    received = [n for _ in consumers for n in out.get(timeout=60)]
    for proc in consumers:
        proc.join(30)
    assert sorted(received) == list(range(200))  # every message once: none lost, none twice
    assert not [p for p in (tmp_path / "q").iterdir() if p.name.endswith(".msg")]
    assert not list((tmp_path / "claimed").iterdir())


BIND_ROUNDS = 20


def _bind_in_rounds(folder, name, barrier) -> None:
    """Bind queue ``name`` to a fresh fanout exchange each round, all binders released together."""
    with _broker(folder) as conn:
        channel = conn.channel()
        for round_ in range(BIND_ROUNDS):
            barrier.wait(30)
            Queue(name, Exchange(f"fanout{round_}", type="fanout"), channel=channel).declare()


def test_filesystem_broker_keeps_every_binding_of_processes_binding_at_once(tmp_path):
    _broker_folders(tmp_path)
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(6)
    binders = [context.Process(target=_bind_in_rounds, args=(tmp_path, f"w{i}", barrier)) for i in range(6)]
    for proc in binders:
        proc.start()
    for proc in binders:
        proc.join(120)
    assert [proc.exitcode for proc in binders] == [0] * 6
    with _broker(tmp_path) as conn:
        channel = conn.channel()
        bound = [sorted(b.queue for b in channel.get_table(f"fanout{r}")) for r in range(BIND_ROUNDS)]
    assert bound == [[f"w{i}" for i in range(6)]] * BIND_ROUNDS  # kombu's own channel loses some


def test_filesystem_broker_unbinds_one_queue_and_reads_an_empty_exchange_file_as_unbound(tmp_path):
    _broker_folders(tmp_path)
    (tmp_path / "c" / "empty.exchange").touch()  # created by a binder that has not written yet
    with _broker(tmp_path) as conn:
        channel = conn.channel()
        assert channel.get_table("empty") == []
        queues = [Queue(n, Exchange("fan", type="fanout"), channel=channel) for n in ("a", "b", "c")]
        for queue in queues:
            queue.declare()
        queues[1].delete()
        assert sorted(b.queue for b in channel.get_table("fan")) == ["a", "c"]
        assert channel.get_table("never-bound") == []


def _bind_and_die_before_the_rename(folder) -> None:
    """Bind queue ``b`` to exchange ``crash`` and die (SIGKILL) when the new table is written, before it is renamed
    into place: a binder killed while writing."""
    def killed(*_args):
        os.kill(os.getpid(), 9)

    os.replace = killed  # this child process's only: the atomic writer's rename
    with _broker(folder) as conn:
        Queue("b", Exchange("crash", type="fanout"), channel=conn.channel()).declare()


def test_filesystem_broker_keeps_the_whole_table_when_a_binder_dies_while_writing_it(tmp_path):
    """(An exchange name no other test binds: kombu keeps the bindings it made in a process-wide state.)"""
    _broker_folders(tmp_path)
    with _broker(tmp_path) as conn:
        Queue("a", Exchange("crash", type="fanout"), channel=conn.channel()).declare()
    binder = multiprocessing.get_context("spawn").Process(target=_bind_and_die_before_the_rename, args=(tmp_path,))
    binder.start()
    binder.join(60)
    assert binder.exitcode == -9
    with _broker(tmp_path) as conn:
        channel = conn.channel()
        assert [b.queue for b in channel.get_table("crash")] == ["a"]  # the old table, whole
        Queue("c", Exchange("crash", type="fanout"), channel=channel).declare()  # the dead binder's lock is gone
        assert sorted(b.queue for b in channel.get_table("crash")) == ["a", "c"]


@pytest.fixture
def settings(tmp_path) -> Settings:
    s = Settings(data_dir=tmp_path / "data", stale_after_s=5.0)
    s.make_dirs()
    return s


def test_claims_are_fenced_and_stale_jobs_are_requeued(settings):
    jobstore.add_scene(settings, "a" * 32, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, "a" * 32, {"max_iters": 5})
    first = jobstore.JOBS.claim(settings, job.id, "elsewhere:1")
    assert first.attempt == 1 and first.state == "running"
    assert jobstore.JOBS.claim(settings, job.id, "elsewhere:2") is None  # fresh lease: not claimable
    nan_point = EvalRecord(elapsed_s=1.0, iteration=3, psnr={"test": float("nan")})
    assert jobstore.JOBS.record_progress(
        settings, job.id, 1, ProgressEvent(stage="train", progress=0.5, history=[nan_point])
    )
    history = jobstore.JOBS.get(settings, job.id).history
    assert [point["psnr"] for point in history] == [{"test": None}]  # NaN never reaches the store

    celery = create_celery(settings)
    assert requeue_stale(settings, celery, jobstore.JOBS) == []
    jobstore.JOBS.renew_lease(settings, job.id, 1)
    with session_scope(settings) as session:  # the worker went silent 10 s ago
        session.get(JobRow, job.id).heartbeat_at = time.time() - 10
    assert requeue_stale(settings, celery, jobstore.JOBS) == [job.id]
    assert [p for p in (settings.broker_dir / "queue").iterdir() if p.name.endswith(".train.msg")]
    requeued = jobstore.JOBS.get(settings, job.id)
    assert requeued.state == "queued" and requeued.requeues == 1

    second = jobstore.JOBS.claim(settings, job.id, "here:2")
    assert second.attempt == 2
    assert not jobstore.JOBS.record_progress(
        settings, job.id, 1, ProgressEvent(stage="train", progress=0.9)
    )  # the old worker is fenced off
    assert not jobstore.JOBS.renew_lease(settings, job.id, 1).owned
    assert jobstore.JOBS.finish(settings, job.id, 2, "succeeded", {"progress": 1.0})
    assert jobstore.JOBS.get(settings, job.id).state == "succeeded"


def test_a_job_whose_local_worker_process_is_gone_is_stale_at_once(settings):
    jobstore.add_scene(settings, "b" * 32, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, "b" * 32, {"max_iters": 5})
    dead = multiprocessing.get_context("spawn").Process(target=time.sleep, args=(0,))
    dead.start()
    dead.join()
    jobstore.JOBS.claim(settings, job.id, f"{socket.gethostname()}:{dead.pid}")
    assert [j.id for j in jobstore.JOBS.stale(settings)] == [job.id]
    jobstore.JOBS.mark_requeued(settings, jobstore.JOBS.stale(settings))
    mine = jobstore.JOBS.claim(settings, job.id, f"{socket.gethostname()}:{os.getpid()}")
    assert mine.attempt == 2 and jobstore.JOBS.stale(settings) == []


def test_cancel_is_immediate_when_queued_and_flagged_when_running(settings):
    jobstore.add_scene(settings, "c" * 32, "room", {"frames": 1}, 10)
    queued = jobstore.create_job(settings, "c" * 32, {"max_iters": 5})
    assert jobstore.JOBS.request_cancel(settings, queued.id).state == "cancelled"
    assert jobstore.JOBS.claim(settings, queued.id, "w:1") is None
    running = jobstore.create_job(settings, "c" * 32, {"max_iters": 5})
    jobstore.JOBS.claim(settings, running.id, "w:1")
    flagged = jobstore.JOBS.request_cancel(settings, running.id)
    assert flagged.state == "running" and flagged.cancel_requested
    assert jobstore.JOBS.renew_lease(settings, running.id, 1).cancel_requested
    with pytest.raises(jobstore.SceneBusy):
        jobstore.delete_scene(settings, "c" * 32)
    assert jobstore.get_scene(settings, "c" * 32) is not None


def test_upload_names_the_engines_scene_file():
    from app.core import storage
    from voxnerf import files  # the engine modules import torch: not at app.uploads.staging's import
    from voxnerf.data import scene
    from voxnerf.inference import render

    assert TRANSFORMS == scene.TRANSFORMS == files.TRANSFORMS
    assert storage.CHECKPOINT == render.CHECKPOINT == files.CHECKPOINT
