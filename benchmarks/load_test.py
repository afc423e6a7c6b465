"""Bounded load test of the service: concurrent ``POST /render`` and uploads at several concurrency levels.

    .venv/bin/python benchmarks/load_test.py [--render-levels 1,2,4,8,16] [--renders-per-client 4]
        [--upload-levels 1,2,4] [--uploads-per-client 2] [--mixed-levels 4+2,8+2] [--limit 4] [--write-docs]

Starts the real service on loopback (a throw-away redis-server with append-only persistence, the uvicorn API
with ``VOXNERF_MAX_CONCURRENT_RENDERS=<limit>``, one train and one render worker), trains one tiny job,
then, per level, runs that many asyncio httpx clients, each sending its requests back to back (renders
alone, uploads alone, then both at once). Per level it reports throughput (successful responses per
second), p50/p95/p99 latency of the successful ones, and the count of every status. Expected: no error at
or below the limit; above it, 429 (with Retry-After) for the surplus and never a 5xx. Exits 1 if that does
not hold. ``--write-docs`` replaces the marked section of docs/scale.md with the results.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import tempfile
import textwrap
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers the service tests use

from docs_section import replace_section  # noqa: E402
from service_fixtures import first_pose, start_redis, start_service, wait_for, zip_scene  # noqa: E402

from voxnerf.synthetic import RoomSpec, make_room_scene  # noqa: E402

DOC = REPO / "docs" / "scale.md"
SECTION = "load-test"  # the marked section of DOC that --write-docs replaces
TRAIN = {"max_iters": 8, "compile": False}  # the load does not depend on how well the model fits


Send = Callable[[httpx.AsyncClient], Awaitable[httpx.Response]]


@dataclass(frozen=True)
class Workload:
    """``clients`` concurrent clients, each sending ``per_client`` requests made by ``send``, back to back."""

    send: Send
    clients: int
    per_client: int


async def _client_loop(client: httpx.AsyncClient, work: Workload, out: list) -> None:
    """One client: record (status, seconds) of each request (status 0: no answer). After a 429 it waits
    ``Retry-After`` seconds before its next request, as a well-behaved client does."""
    for _ in range(work.per_client):
        started = time.perf_counter()
        try:
            response = await work.send(client)
        except httpx.HTTPError:
            out.append((0, time.perf_counter() - started))
            continue
        out.append((response.status_code, time.perf_counter() - started))
        if response.status_code == 429:
            await asyncio.sleep(float(response.headers.get("retry-after", "1")))


def _summary(work: Workload, samples: list[tuple[int, float]], wall: float) -> dict:
    ok_ms = np.asarray([s for status, s in samples if status in (200, 201)]) * 1000
    refused_ms = np.asarray([s for status, s in samples if status == 429]) * 1000
    statuses = Counter(status for status, _ in samples)
    pct = {f"p{q}_ms": float(np.percentile(ok_ms, q)) if len(ok_ms) else None for q in (50, 95, 99)}
    return {
        "clients": work.clients,
        "requests": len(samples),
        "ok": len(ok_ms),
        "ok_per_s": len(ok_ms) / wall,
        "wall_s": wall,
        **pct,
        "p50_429_ms": float(np.percentile(refused_ms, 50)) if len(refused_ms) else None,
        "statuses": {str(k): v for k, v in sorted(statuses.items())},
    }


async def _run_workload(client: httpx.AsyncClient, work: Workload, out: list) -> float:
    """All clients of one workload; returns the seconds until the last of them finished."""
    started = time.perf_counter()
    await asyncio.gather(*(_client_loop(client, work, out) for _ in range(work.clients)))
    return time.perf_counter() - started


async def run_level(base_url: str, workloads: dict[str, Workload]) -> dict[str, dict]:
    """Run every workload at the same time; per workload: throughput, latency and the statuses seen."""
    total = sum(w.clients for w in workloads.values())
    limits = httpx.Limits(max_connections=total, max_keepalive_connections=total)
    samples: dict[str, list] = {name: [] for name in workloads}
    async with httpx.AsyncClient(base_url=base_url, timeout=300, limits=limits, trust_env=False) as client:
        walls = await asyncio.gather(
            *(_run_workload(client, work, samples[name]) for name, work in workloads.items())
        )
    return {
        name: _summary(work, samples[name], wall)
        for (name, work), wall in zip(workloads.items(), walls, strict=True)
    }


def check(results: dict, limit: int) -> list[str]:
    """What violates the contract: a render refused at or below the limit, any refused upload, any 5xx or
    missing answer."""
    problems = []
    for row in results["rows"]:
        where = f"{row['kind']} x{row['clients']} ({row['level']})"
        bad = {s: n for s, n in row["statuses"].items() if s not in ("200", "201", "429")}
        if bad:
            problems.append(f"{where}: {bad}")
        refused = row["statuses"].get("429", 0)
        if refused and (row["kind"] == "upload" or row["clients"] <= limit):
            problems.append(f"{where}: {refused} refused at or below the limit")
    return problems


def _fmt(ms: float | None) -> str:
    return "-" if ms is None else f"{ms:.0f}"


def markdown(results: dict, command: str) -> str:
    env = results["environment"]
    setting = textwrap.fill(
        f"Measured {env['date']} on {env['machine']}, {env['cpus']} CPU cores shared with other jobs (load "
        f"average {env['load_before']} before, {env['load_after']} after), everything on one machine over "
        f"loopback: redis-server, one API process (`VOXNERF_MAX_CONCURRENT_RENDERS={results['limit']}`), "
        "one render worker process and one idle train worker, all on the CPU. Command:",
        width=110,
    )
    lines = [
        setting,
        "",
        "```",
        command,
        "```",
        "",
        "| level | requests | clients | sent | ok | ok/s | p50 ms | p95 ms | p99 ms | 429 p50 ms "
        "| statuses |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    names = {
        "render": f"POST /render {results['render_size']} PNG",
        "upload": f"POST /scenes ({results['zip_kib']} KiB zip)",
    }
    for r in results["rows"]:
        statuses = ", ".join(f"{s}: {n}" for s, n in r["statuses"].items())
        lines.append(
            f"| {r['level']} | {names[r['kind']]} | {r['clients']} | {r['requests']} | {r['ok']} | "
            f"{r['ok_per_s']:.1f} | {_fmt(r['p50_ms'])} | {_fmt(r['p95_ms'])} | {_fmt(r['p99_ms'])} | "
            f"{_fmt(r['p50_429_ms'])} | {statuses} |"
        )
    note = (
        "ok/s: successful answers per second, from the first request of the row's clients to the last "
        "answer. Latency percentiles are over the successful requests only; 429 p50 is how fast a refusal "
        "comes. A client that gets 429 waits `Retry-After` (1 s) before its next request."
    )
    lines += ["", textwrap.fill(note, width=110)]
    return "\n".join(lines)


def _levels(text: str) -> list[tuple[int, int]]:
    """``"4+2,8+2"`` -> [(4, 2), (8, 2)]: render clients + upload clients of each mixed level."""
    return [tuple(int(n) for n in item.split("+")) for item in text.split(",") if item]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--render-levels", default="1,2,4,8,16", help="concurrent render clients per level")
    parser.add_argument("--renders-per-client", type=int, default=4)
    parser.add_argument("--upload-levels", default="1,2,4", help="concurrent upload clients per level")
    parser.add_argument("--uploads-per-client", type=int, default=2)
    parser.add_argument(
        "--mixed-levels", default="4+2,8+2", help="render clients + upload clients, run at the same time"
    )
    parser.add_argument("--limit", type=int, default=4, help="VOXNERF_MAX_CONCURRENT_RENDERS of the API")
    parser.add_argument("--write-docs", action="store_true", help=f"update the results section of {DOC}")
    args = parser.parse_args()
    render_levels = [int(x) for x in args.render_levels.split(",") if x]
    upload_levels = [int(x) for x in args.upload_levels.split(",") if x]
    results: dict = {
        "environment": {
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": f"{platform.system()} {platform.machine()}",
            "cpus": os.cpu_count(),
            "load_before": " ".join(f"{x:.2f}" for x in os.getloadavg()),
        },
        "limit": args.limit,
        "render_size": "64x48",
    }
    with tempfile.TemporaryDirectory(prefix="voxnerf-load-") as tmp:
        root = Path(tmp)
        scene_dir = make_room_scene(
            root / "room", RoomSpec(width=64, height=48, n_frames=120, gap_len=20, prior_max_points=100_000)
        )
        small = RoomSpec(
            width=64, height=48, n_frames=24, train_every=3, n_gaps=1, gap_len=10, prior_max_points=20_000
        )
        upload_dir = make_room_scene(root / "upload", small)
        upload_zip = zip_scene(upload_dir)
        results["zip_kib"] = len(upload_zip) // 1024
        redis = start_redis(root / "redis", appendonly=True)
        settings = {"VOXNERF_MAX_CONCURRENT_RENDERS": str(args.limit), "OMP_NUM_THREADS": "1"}
        service = start_service(root / "service", broker_url=redis.url, settings=settings)
        try:
            with service.client(timeout_s=120) as client:
                files = {"file": ("room.zip", zip_scene(scene_dir), "application/zip")}
                scene = client.post("/scenes", files=files)
                scene.raise_for_status()
                job = client.post(f"/scenes/{scene.json()['id']}/jobs", json=TRAIN).json()
                wait_for(
                    lambda: client.get(f"/jobs/{job['id']}").json()["state"] == "succeeded",
                    600,
                    "the load-test model to train",
                    1.0,
                )
                body = {"job_id": job["id"], "transform_matrix": first_pose(scene_dir)}
                client.post("/render", json=body).raise_for_status()  # warm-up: loads the model

            def render(c: httpx.AsyncClient) -> Awaitable[httpx.Response]:
                return c.post("/render", json=body)

            def upload(c: httpx.AsyncClient) -> Awaitable[httpx.Response]:
                return c.post("/scenes", files={"file": ("upload.zip", upload_zip, "application/zip")})

            levels: list[tuple[str, dict[str, Workload]]] = [
                ("render", {"render": Workload(render, n, args.renders_per_client)}) for n in render_levels
            ]
            levels += [
                ("upload", {"upload": Workload(upload, n, args.uploads_per_client)}) for n in upload_levels
            ]
            levels += [
                (
                    "mixed",
                    {
                        "render": Workload(render, n_render, args.renders_per_client),
                        "upload": Workload(upload, n_upload, args.uploads_per_client),
                    },
                )
                for n_render, n_upload in _levels(args.mixed_levels)
            ]
            results["rows"] = []
            for level, workloads in levels:
                for kind, row in asyncio.run(run_level(service.base_url, workloads)).items():
                    results["rows"].append({"level": level, "kind": kind, **row})
                    print(level, kind, json.dumps(row), flush=True)
        finally:
            service.stop()
            redis.stop()
    results["environment"]["load_after"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    command = ".venv/bin/python benchmarks/load_test.py " + " ".join(sys.argv[1:])
    text = markdown(results, command.strip())
    print(text)
    problems = check(results, args.limit)
    if args.write_docs:
        replace_section(DOC, SECTION, text)
    if problems:
        print("contract violated:", *problems, sep="\n  ", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
