"""A soak test of the whole service (issue #42, item 9): many clients at once while processes die.

Real processes, all on loopback: a uvicorn API, a redis-server broker (append-only file, as in
docker-compose.yml), and three Celery workers (train, render, outputs; concurrency 1 each). ``CLIENTS`` client
threads upload small scenes, train short jobs, render and request videos for ``LOAD_S`` seconds, while a chaos
thread SIGKILLs each worker in turn (then starts it again) and restarts redis-server. One job has been trained
before the load starts, so renders and videos are asked for from its first second. Then the load stops and the
service drains.

At the end:
- every job and every output a client was told was accepted (202) is in a final state, and no job or output
  was lost: the service lists exactly those, plus one ``failed`` row per submission the broker refused while it
  was down (the client was answered 503 for each); no id twice;
- every accepted job succeeded (a killed worker's job was requeued and resumed), every accepted video
  succeeded, and no request was answered 500;
- the API process's resident memory grew by less than ``API_RSS_GROWTH`` over the run (from when the first
  upload had been served).

Its figures are printed (``-s``); docs/stability.md records a run of its earlier 90 s form. The durations are
bounded: ``LOAD_S`` of load, at most ``DRAIN_S`` to drain.
"""

from __future__ import annotations

import contextlib
import itertools
import random
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import httpx
import numpy as np
import pytest
from service_fixtures import (
    RedisServer,
    Service,
    start_redis,
    start_service,
    wait_for,
    wait_until_succeeded,
    zip_scene,
)
from synthetic_fixtures import make_micro_scene

pytestmark = pytest.mark.slow

MiB = 1024 * 1024
CLIENTS = 3
LOAD_S = 45.0
DRAIN_S = 360.0
JOBS_PER_CLIENT = 4
VIDEOS_PER_CLIENT = 2
SCENES_PER_CLIENT = 2
API_RSS_GROWTH = 64 * MiB
TINY = {"max_iters": 3, "compile": False, "downscale": 2}
VIDEO = {"path": "orbit", "frames": 2, "width": 16, "height": 12}
LONG_JOB = {"max_seconds": 12, "compile": False, "downscale": 2}  # training when its worker is killed
LONG_VIDEO = {"path": "orbit", "frames": 300, "width": 32, "height": 24}  # running when its worker is killed
FINAL = ("succeeded", "failed", "cancelled")
SETTINGS = {
    "VOXNERF_HEARTBEAT_S": "1",
    "VOXNERF_STALE_AFTER_S": "8",  # a killed worker's job is requeued this soon
    "VOXNERF_RESEND_QUEUED_AFTER_S": "20",  # a message lost in a broker restart is sent again
    "VOXNERF_RENDER_TIMEOUT_S": "10",  # the render the killed render worker held is answered 504 this soon
    "VOXNERF_CHECKPOINT_EVERY_S": "1",
    "OMP_NUM_THREADS": "1",
}
# (seconds into the load, what happens): each worker is killed once, redis-server restarts once.
CHAOS = [(6.0, "kill train"), (16.0, "restart redis"), (26.0, "kill outputs"), (36.0, "kill render")]
DOWN_S = 3.0  # how long a killed process or the stopped broker stays down
RUNNING_WAIT_S = 15.0  # how long the chaos thread waits for work to interrupt before killing a worker anyway


@dataclass
class Tally:
    """What the clients were answered, shared by their threads."""

    jobs: list[str] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)
    scenes: list[str] = field(default_factory=list)
    answers: Counter = field(default_factory=Counter)  # (action, status code)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def note(self, action: str, response: httpx.Response | None) -> None:
        with self.lock:
            self.answers[(action, response.status_code if response is not None else "no answer")] += 1


@pytest.fixture(scope="module")
def redis(tmp_path_factory) -> Iterator[RedisServer]:
    server = start_redis(tmp_path_factory.mktemp("soak-redis"), appendonly=True)
    yield server
    server.stop()


@pytest.fixture(scope="module")
def service(tmp_path_factory, redis) -> Iterator[Service]:
    svc = start_service(tmp_path_factory.mktemp("soak"), broker_url=redis.url, settings=SETTINGS, workers=False)
    try:
        for queue in ("train", "render", "outputs"):
            svc.start_worker(queue)
        svc.wait_healthy()
    except BaseException:
        print(svc.logs())
        svc.stop()
        raise
    yield svc
    svc.stop()


def _rss(pid: int) -> int:
    with open(f"/proc/{pid}/status") as status:
        line = next(line for line in status if line.startswith("VmRSS:"))
    return int(line.split()[1]) * 1024


def _post(client: httpx.Client, tally: Tally, action: str, path: str, **kwargs) -> httpx.Response | None:
    try:
        response = client.post(path, **kwargs)
    except httpx.HTTPError:  # a refused connection is not expected: the API never stops here
        tally.note(action, None)
        return None
    tally.note(action, response)
    return response


def _client_loop(service: Service, tally: Tally, scene_zip: bytes, until: float, seed: int) -> None:
    rng = random.Random(seed)
    mine = {"scenes": [], "jobs": 0, "videos": 0}
    with service.client(timeout_s=60) as client:
        for step in itertools.count():
            if time.monotonic() > until:
                return
            if not mine["scenes"] or (len(mine["scenes"]) < SCENES_PER_CLIENT and step % 7 == 3):
                response = _post(client, tally, "upload", "/scenes",
                                 files={"file": ("room.zip", scene_zip, "application/zip")})
                if response is not None and response.status_code == 201:
                    mine["scenes"].append(response.json()["id"])
                    with tally.lock:
                        tally.scenes.append(response.json()["id"])
                else:
                    time.sleep(1.0)  # 429: the other clients' uploads are in progress
                continue
            succeeded = [j["id"] for j in client.get("/jobs", params={"limit": 1000}).json()
                         if j["state"] == "succeeded"]
            choice = rng.random()
            if choice < 0.3 and mine["jobs"] < JOBS_PER_CLIENT:
                response = _post(client, tally, "train", f"/scenes/{rng.choice(mine['scenes'])}/jobs", json=TINY)
                if response is not None and response.status_code == 202:
                    mine["jobs"] += 1
                    with tally.lock:
                        tally.jobs.append(response.json()["id"])
            elif choice < 0.45 and succeeded and mine["videos"] < VIDEOS_PER_CLIENT:
                response = _post(client, tally, "video", f"/jobs/{rng.choice(succeeded)}/videos", json=VIDEO)
                if response is not None and response.status_code == 202:
                    mine["videos"] += 1
                    with tally.lock:
                        tally.outputs.append(response.json()["id"])
            elif succeeded:
                _post(client, tally, "render", "/render", json={
                    "job_id": rng.choice(succeeded), "transform_matrix": np.eye(4).tolist(), "width": 16,
                    "height": 12})
            time.sleep(0.2)


def _running(client: httpx.Client, queue: str) -> str | None:
    """The id of a job (``train``) or output (``outputs``) running now, if any."""
    jobs = client.get("/jobs", params={"limit": 1000}).json()
    if queue == "train":
        return next((j["id"] for j in jobs if j["state"] == "running"), None)
    outputs = (o for j in jobs if j["state"] == "succeeded" for o in client.get(f"/jobs/{j['id']}/outputs").json())
    return next((o["id"] for o in outputs if o["state"] == "running"), None)


def _request_long_job(client: httpx.Client, tally: Tally) -> None:
    with tally.lock:
        scenes = list(tally.scenes)
    if scenes:
        response = _post(client, tally, "train", f"/scenes/{scenes[0]}/jobs", json=LONG_JOB)
        if response is not None and response.status_code == 202:
            with tally.lock:
                tally.jobs.append(response.json()["id"])


def _request_long_video(client: httpx.Client, tally: Tally) -> None:
    succeeded = [j["id"] for j in client.get("/jobs", params={"limit": 1000}).json() if j["state"] == "succeeded"]
    if succeeded:
        response = _post(client, tally, "video", f"/jobs/{succeeded[0]}/videos", json=LONG_VIDEO)
        if response is not None and response.status_code == 202:
            with tally.lock:
                tally.outputs.append(response.json()["id"])


def _chaos(service: Service, redis: RedisServer, tally: Tally, started: float, log: list[str]) -> None:
    """Each fault of CHAOS at its time; a worker is killed while it runs a job or an output when one starts
    within ``RUNNING_WAIT_S`` (the log says what the kill interrupted). Before the train worker is killed a longer
    job (``LONG_JOB``), and before the outputs worker a longer video (``LONG_VIDEO``), is requested, so that one is
    running (the tiny jobs and videos of the load finish in under a second on an idle machine)."""
    with service.client() as client:
        for at, what in CHAOS:
            time.sleep(max(0.0, started + at - time.monotonic()))
            verb, name = what.split()
            if verb == "kill":
                interrupted = None
                if name == "train":
                    _request_long_job(client, tally)
                if name == "outputs":
                    _request_long_video(client, tally)
                if name in ("train", "outputs"):
                    with contextlib.suppress(AssertionError):
                        interrupted = wait_for(lambda name=name: _running(client, name), RUNNING_WAIT_S,
                                               f"work on the {name} queue", 0.3)
                service.kill(name)
                time.sleep(DOWN_S)
                service.start_worker(name)
                what = f"{what} (interrupting {interrupted or 'nothing running'})"
            else:
                redis.stop()
                time.sleep(DOWN_S)
                redis.start()
            log.append(f"{time.monotonic() - started:.0f} s: {what}")


def _sample_memory(service: Service, samples: list[int], stop: threading.Event) -> None:
    pid = service.procs["api"].pid
    while not stop.wait(0.5):
        samples.append(_rss(pid))


def test_soak(service, redis, tmp_path_factory):
    scene_zip = zip_scene(make_micro_scene(tmp_path_factory, "soak-scene"))
    tally = Tally()
    # the first upload and its job warm the API up (its memory is measured from here), and the clients can render
    # and ask for videos from the load's first second, however long jobs take on a loaded machine
    with service.client() as client:
        first = client.post("/scenes", files={"file": ("room.zip", scene_zip, "application/zip")})
        assert first.status_code == 201, first.text
        tally.scenes.append(first.json()["id"])
        job = client.post(f"/scenes/{first.json()['id']}/jobs", json=TINY)
        assert job.status_code == 202, job.text
        tally.jobs.append(job.json()["id"])
        wait_until_succeeded(service, client, job.json()["id"], DRAIN_S)
    baseline = _rss(service.procs["api"].pid)
    samples: list[int] = [baseline]
    stop_sampling = threading.Event()
    sampler = threading.Thread(target=_sample_memory, args=(service, samples, stop_sampling), daemon=True)
    sampler.start()
    chaos_log: list[str] = []
    started = time.monotonic()
    until = started + LOAD_S
    threads = [threading.Thread(target=_client_loop, args=(service, tally, scene_zip, until, seed), daemon=True)
               for seed in range(CLIENTS)]
    chaos = threading.Thread(target=_chaos, args=(service, redis, tally, started, chaos_log), daemon=True)
    for thread in (*threads, chaos):
        thread.start()
    for thread in (*threads, chaos):
        thread.join(LOAD_S + 120)
        assert not thread.is_alive(), "a client or the chaos thread is stuck"
    load_s = time.monotonic() - started

    with service.client() as client:
        def drained():
            jobs = client.get("/jobs", params={"limit": 1000}).json()
            outputs = [o for j in jobs for o in client.get(f"/jobs/{j['id']}/outputs").json()]
            return (jobs, outputs) if all(r["state"] in FINAL for r in (*jobs, *outputs)) else None

        try:
            jobs, outputs = wait_for(drained, DRAIN_S, "every job and output to reach a final state", 2.0)
        except AssertionError:
            pytest.fail(f"not drained after {DRAIN_S:.0f} s\n{service.logs()}")
    drain_s = time.monotonic() - started - load_s
    stop_sampling.set()
    sampler.join(5)

    job_ids = [j["id"] for j in jobs]
    output_ids = [o["id"] for o in outputs]
    assert len(set(job_ids)) == len(job_ids) and len(set(output_ids)) == len(output_ids), "an id listed twice"
    refused_by_broker = [j for j in jobs if j["id"] not in tally.jobs]
    assert all(j["state"] == "failed" and "the broker refused it" in (j["error"] or "")
               for j in refused_by_broker), refused_by_broker
    assert len(refused_by_broker) == tally.answers[("train", 503)], (refused_by_broker, tally.answers)
    assert set(tally.jobs) <= set(job_ids), "an accepted job was lost"
    refused_outputs = [o for o in outputs if o["id"] not in tally.outputs]
    assert all(o["state"] == "failed" and "the broker refused it" in (o["error"] or "")
               for o in refused_outputs), refused_outputs
    assert len(refused_outputs) == tally.answers[("video", 503)], (refused_outputs, tally.answers)
    assert set(tally.outputs) <= set(output_ids), "an accepted output was lost"
    accepted_jobs = [j for j in jobs if j["id"] in tally.jobs]
    accepted_outputs = [o for o in outputs if o["id"] in tally.outputs]
    not_done = [(j["id"], j["state"], j["error"]) for j in accepted_jobs if j["state"] != "succeeded"]
    assert not not_done, f"{not_done}\n{service.logs()}"
    not_done = [(o["id"], o["state"], o["error"]) for o in accepted_outputs if o["state"] != "succeeded"]
    assert not not_done, f"{not_done}\n{service.logs()}"
    assert not [key for key in tally.answers if key[1] in (500, "no answer")], tally.answers
    assert tally.jobs and tally.outputs and tally.answers[("render", 200)], f"too little load: {tally.answers}"
    growth = max(samples) - baseline
    requeued = sum(j["requeues"] for j in accepted_jobs)
    requeued_outputs = sum(o["requeues"] for o in accepted_outputs)
    print(f"\nsoak: {CLIENTS} clients, {load_s:.0f} s of load, drained in {drain_s:.0f} s; chaos: {chaos_log}\n"
          f"  scenes {len(tally.scenes)}, jobs accepted {len(tally.jobs)} (all succeeded, {requeued} requeues, "
          f"attempts {sorted(Counter(j['attempt'] for j in accepted_jobs).items())}), "
          f"refused by the broker {len(refused_by_broker)}; videos accepted {len(tally.outputs)} (all succeeded, "
          f"{requeued_outputs} requeues), refused {len(refused_outputs)}\n"
          f"  answers {sorted((f'{a} {c}', n) for (a, c), n in tally.answers.items())}\n"
          f"  API RSS {baseline / MiB:.0f} MiB after the first upload, peak {max(samples) / MiB:.0f} MiB "
          f"(+{growth / MiB:.0f} MiB), {len(samples)} samples")
    assert growth < API_RSS_GROWTH, f"the API's memory grew by {growth / MiB:.0f} MiB"
