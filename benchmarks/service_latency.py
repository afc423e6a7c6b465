"""POST /render latency (320x240 PNG, warm render worker) and job-submission throughput, in both broker modes.

    .venv/bin/python benchmarks/service_latency.py [--renders 5] [--jobs 60] [--write-docs]

Starts the real service (uvicorn + Celery worker processes, loopback only) on a temporary data directory:
first on the embedded default (filesystem queue + SQLite), then on a throw-away redis-server with the same
data directory. One short training job provides the model. Every loop is bounded. With ``--write-docs`` the
results replace the marked section of docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers the service tests use

from docs_section import replace_section  # noqa: E402
from service_fixtures import first_pose, start_redis, start_service, wait_for, zip_scene  # noqa: E402

from voxnerf.synthetic import RoomSpec, make_room_scene  # noqa: E402

DOC = REPO / "docs" / "performance.md"
SECTION = "service-latency"  # the marked section of DOC that --write-docs replaces
TRAIN = {"max_iters": 8, "compile": False}  # latency does not depend on how well the model fits


def render_times(
    client, job_id: str, pose: list, count: int, size: tuple[int, int], warmup: int = 1
) -> list[float]:
    """Seconds of ``count`` sequential POST /render of a ``size`` PNG, after ``warmup`` untimed ones."""
    body = {"job_id": job_id, "transform_matrix": pose, "width": size[0], "height": size[1], "format": "png"}
    for _ in range(warmup):  # loads the model into the render worker's cache
        client.post("/render", json=body).raise_for_status()
    times = []
    for _ in range(count):
        started = time.perf_counter()
        response = client.post("/render", json=body)
        times.append(time.perf_counter() - started)
        response.raise_for_status()
        assert response.headers["content-type"] == "image/png"
    return times


def measure_renders(
    client, job_id: str, pose: list, count: int, size: tuple[int, int], warmup: int = 1
) -> dict:
    """Latency of ``count`` sequential POST /render of a ``size`` PNG, after ``warmup`` untimed ones."""
    ms = np.asarray(render_times(client, job_id, pose, count, size, warmup)) * 1000
    return {
        "n": count,
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
    }


def measure_submissions(service, scene_id: str, count: int, threads: int) -> dict:
    """Jobs accepted per second (POST /scenes/{id}/jobs -> 202), sequentially and from ``threads`` clients.

    The train worker is stopped first, so the numbers are the API's (job row + broker message) alone; every
    submitted job is cancelled afterwards (queued jobs cancel at once).
    """

    def submit(n: int) -> list[str]:
        with service.client() as client:
            ids = []
            for _ in range(n):
                response = client.post(f"/scenes/{scene_id}/jobs", json={"max_iters": 10})
                response.raise_for_status()
                ids.append(response.json()["id"])
            return ids

    started = time.perf_counter()
    ids = submit(count)
    sequential = count / (time.perf_counter() - started)
    started = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        batches = list(pool.map(submit, [count // threads] * threads))
    concurrent = sum(map(len, batches)) / (time.perf_counter() - started)
    with service.client() as client:
        for job_id in ids + [i for batch in batches for i in batch]:
            client.post(f"/jobs/{job_id}/cancel")
    return {"n": count, "threads": threads, "sequential_per_s": sequential, "concurrent_per_s": concurrent}


def run_mode(mode: str, root: Path, data_dir: Path, scene_dir: Path, args, state: dict) -> dict:
    redis = start_redis(root / f"redis-{mode}") if mode == "redis" else None
    # The submission loops queue 2 x --jobs jobs at once: the queue's limit must not answer them 429.
    settings = {"VOXNERF_DATA_DIR": str(data_dir), "VOXNERF_MAX_QUEUED_JOBS": str(2 * args.jobs + 10)}
    service = start_service(root / mode, broker_url=redis.url if redis else None, settings=settings)
    try:
        with service.client(timeout_s=120) as client:
            if "job_id" not in state:
                scene = client.post(
                    "/scenes", files={"file": ("room.zip", zip_scene(scene_dir), "application/zip")}
                )
                scene.raise_for_status()
                state["scene_id"] = scene.json()["id"]
                job = client.post(f"/scenes/{state['scene_id']}/jobs", json=TRAIN).json()
                wait_for(
                    lambda: client.get(f"/jobs/{job['id']}").json()["state"] == "succeeded",
                    600,
                    "the benchmark model to train",
                    1.0,
                )
                state["job_id"] = job["id"]
            pose = first_pose(scene_dir)
            renders = measure_renders(client, state["job_id"], pose, args.renders, (320, 240))
            tiny = measure_renders(client, state["job_id"], pose, args.tiny_renders, (8, 6))
        service.kill("train")
        submissions = measure_submissions(service, state["scene_id"], args.jobs, args.threads)
        return {"render_320x240_png": renders, "render_8x6_png": tiny, "job_submission": submissions}
    finally:
        service.stop()
        if redis is not None:
            redis.stop()


def markdown(results: dict, command: str) -> str:
    env = results["environment"]
    lines = [
        f"Measured {env['date']} on {env['machine']} ({env['cpus']} CPUs, load average {env['load']} "
        "at start), "
        f"one render worker and one train worker (idle), loopback HTTP. Command:",
        "",
        "```",
        command,
        "```",
        "",
        "| mode | POST /render 320x240 PNG p50 | p95 | min / max | 8x6 PNG p50 / p95 (service overhead) | "
        f"job submissions/s (1 client) | ({results['embedded']['job_submission']['threads']} clients) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for mode in ("embedded", "redis"):
        r, t, s = (results[mode][k] for k in ("render_320x240_png", "render_8x6_png", "job_submission"))
        lines.append(
            f"| {mode} | {r['p50_ms']:.0f} ms | {r['p95_ms']:.0f} ms | "
            f"{r['min_ms']:.0f} / {r['max_ms']:.0f} ms | {t['p50_ms']:.0f} / {t['p95_ms']:.0f} ms | "
            f"{s['sequential_per_s']:.1f} | {s['concurrent_per_s']:.1f} |"
        )
    lines += [
        "",
        f"{results['embedded']['render_320x240_png']['n']} timed 320x240 renders and "
        f"{results['embedded']['render_8x6_png']['n']} timed 8x6 renders per mode, each after one warm-up "
        f"render; {results['embedded']['job_submission']['n']} jobs per submission loop. An 8x6 render "
        "costs the engine almost nothing: its latency is the service's own (HTTP, queue, result file).",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--renders", type=int, default=5, help="timed renders per mode")
    parser.add_argument("--tiny-renders", type=int, default=20, help="timed 8x6 renders per mode")
    parser.add_argument("--jobs", type=int, default=60, help="jobs submitted per submission loop")
    parser.add_argument("--threads", type=int, default=4, help="concurrent clients in the second loop")
    parser.add_argument("--write-docs", action="store_true", help=f"update the results section of {DOC}")
    args = parser.parse_args()
    results: dict = {
        "environment": {
            "date": time.strftime("%Y-%m-%d"),
            "machine": f"{platform.system()} {platform.machine()}",
            "cpus": os.cpu_count(),
            "load": " ".join(f"{x:.2f}" for x in os.getloadavg()),
        }
    }
    state: dict = {}
    with tempfile.TemporaryDirectory(prefix="voxnerf-bench-") as tmp:
        root = Path(tmp)
        scene_dir = make_room_scene(
            root / "room", RoomSpec(width=64, height=48, n_frames=120, gap_len=20, prior_max_points=100_000)
        )
        for mode in ("embedded", "redis"):
            results[mode] = run_mode(mode, root, root / "data", scene_dir, args, state)
            print(mode, json.dumps(results[mode]), flush=True)
    command = ".venv/bin/python benchmarks/service_latency.py " + " ".join(sys.argv[1:])
    text = markdown(results, command.strip())
    print(text)
    if args.write_docs:
        replace_section(DOC, SECTION, text)


if __name__ == "__main__":
    main()
