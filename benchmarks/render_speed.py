"""The fast render path against the full one, side by side in one run: frame times in process, POST /render
latency through the service, and held-out PSNR of both paths.

    .venv/bin/python benchmarks/render_speed.py [--room-seconds 60] [--redkitchen ../shared/data/redkitchen
        --redkitchen-seconds 300 --downscale 2] [--renders 15] [--out DIR] [--write-docs]

1. A synthetic 160x120 room is uploaded to the real service on its embedded default (uvicorn, filesystem
   queue, SQLite, one train and one render worker) and trained there for ``--room-seconds``, as a new user would.
2. In process, on that run (and on redkitchen trained in process when ``--redkitchen`` is given): 320x240 and
   640x480 frames of held-out poses, each rendered by both paths in turn (the full path warm: compiled before
   timing, as a long-lived worker has it), and the held-out PSNR of every evaluation view by both paths.
3. Through the service: ``--renders`` timed POST /render of a 320x240 PNG (after one warm-up), with the render
   workers on the fast path, then the full path, then the fast path again (``VOXNERF_RENDER_PATH``), so drift in
   the machine's load shows as a difference between the two fast rounds.

Results go to ``--out`` (results.json, table.md; default benchmarks/results/render_speed/); ``--write-docs`` puts
the table into docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers the service tests use

from docs_section import publish  # noqa: E402
from service_fixtures import start_service, wait_for, zip_scene  # noqa: E402

from voxnerf.cameras.rules import resolve_intrinsics  # noqa: E402
from voxnerf.config import TrainConfig  # noqa: E402
from voxnerf.data.scene import load_scene  # noqa: E402
from voxnerf.inference.evaluation import evaluate_views  # noqa: E402
from voxnerf.inference.render import load_model, render  # noqa: E402
from voxnerf.synthetic import RoomSpec, make_room_scene  # noqa: E402
from voxnerf.trainer import train  # noqa: E402
from voxnerf.training.eval_passes import eval_views_of  # noqa: E402

DOC = REPO / "docs" / "performance.md"
SECTION = "render-speed"
SIZES = ((320, 240), (640, 480))
PATHS = ("fast", "full")


def percentiles(seconds: list[float]) -> dict:
    ms = np.asarray(seconds) * 1000
    return {"n": len(ms), "p50_ms": float(np.percentile(ms, 50)), "p95_ms": float(np.percentile(ms, 95))}


def held_out_poses(scene_dir: Path, count: int) -> list[np.ndarray]:
    scene = load_scene(scene_dir, load_images=False)
    frames = [i for name in scene.eval_split_names for i in scene.splits[name]]
    picks = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    return [scene.frames[frames[i]].c2w for i in picks]


def frame_times(run_dir: Path, scene_dir: Path, count: int) -> dict:
    """Per size and path: p50/p95 of ``count`` held-out poses, the two paths alternating pose by pose."""
    trained = load_model(run_dir, "cpu")
    poses = held_out_poses(scene_dir, count)
    results = {}
    for width, height in SIZES:
        camera = resolve_intrinsics(trained.default_intrinsics.undistorted(), width=width, height=height)
        for path in PATHS:  # warm-up: the full path compiles here, once per model
            render(trained, poses[0], camera, ("rgb",), path=path)
        times: dict[str, list[float]] = {path: [] for path in PATHS}
        for pose in poses:
            for path in PATHS:
                started = time.perf_counter()
                render(trained, pose, camera, ("rgb",), path=path)
                times[path].append(time.perf_counter() - started)
        results[f"{width}x{height}"] = {path: percentiles(t) for path, t in times.items()}
        print(f"  {width}x{height}:", json.dumps(results[f"{width}x{height}"]), flush=True)
    return results


def held_out_psnr(run_dir: Path, scene_dir: Path, downscale: int) -> dict:
    """Mean PSNR per evaluation split, rendered by each path, at the resolution the run trained at."""
    trained = load_model(run_dir, "cpu")
    scene = load_scene(scene_dir, downscale=downscale)
    views = eval_views_of(scene, trained.model.transform)
    results = {}
    for path in PATHS:
        started = time.perf_counter()
        metrics = evaluate_views(trained.model, views, trained.model.config, lpips=False, path=path)
        results[path] = {split: m["psnr"] for split, m in metrics.items()}
        results[path]["seconds"] = time.perf_counter() - started
    print("  psnr:", json.dumps(results), flush=True)
    return results


def service_latency(root: Path, data_dir: Path, job_id: str | None, scene_dir: Path, args) -> tuple[str, dict]:
    """Train the room in the service when ``job_id`` is None; then POST /render p50/p95 per render path."""
    results = {}
    for round_no, path in enumerate(("fast", "full", "fast")):
        settings = {"VOXNERF_DATA_DIR": str(data_dir), "VOXNERF_RENDER_PATH": path}
        service = start_service(root / f"service-{round_no}", settings=settings)
        try:
            with service.client(timeout_s=300) as client:
                if job_id is None:
                    job_id = train_in_service(client, scene_dir, args.room_seconds)
                pose = held_out_poses(scene_dir, 1)[0].tolist()
                body = {"job_id": job_id, "transform_matrix": pose, "width": 320, "height": 240, "format": "png"}
                client.post("/render", json=body).raise_for_status()  # loads the model (and compiles: full)
                times = []
                for _ in range(args.renders):
                    started = time.perf_counter()
                    client.post("/render", json=body).raise_for_status()
                    times.append(time.perf_counter() - started)
                results[f"{path}-{round_no}"] = percentiles(times)
                print(f"  service {path} (round {round_no}):", json.dumps(results[f"{path}-{round_no}"]), flush=True)
        finally:
            service.stop()
    return job_id, results


def train_in_service(client, scene_dir: Path, seconds: float) -> str:
    scene = client.post("/scenes", files={"file": ("room.zip", zip_scene(scene_dir), "application/zip")})
    scene.raise_for_status()
    job = client.post(f"/scenes/{scene.json()['id']}/jobs", json={"max_seconds": seconds}).json()
    wait_for(lambda: client.get(f"/jobs/{job['id']}").json()["state"] == "succeeded", 30 * seconds + 600,
             "the room to train", 1.0)
    return job["id"]


def markdown(results: dict, command: str) -> str:
    env = results["environment"]
    lines = [
        f"Measured {env['date']} on {env['machine']} ({env['cpus']} CPUs, torch {env['torch']}, load average "
        f"{env['load']} at start). Command:", "", "```", command, "```", "",
        "| scene | frame | fast p50 / p95 | full p50 / p95 | full / fast |", "| --- | --- | --- | --- | --- |",
    ]
    for scene, r in results["scenes"].items():
        for size, t in r["frame_times"].items():
            fast, full = t["fast"], t["full"]
            lines.append(f"| {scene} | {size} in process | {fast['p50_ms']:.0f} / {fast['p95_ms']:.0f} ms | "
                         f"{full['p50_ms']:.0f} / {full['p95_ms']:.0f} ms | {full['p50_ms'] / fast['p50_ms']:.2f}x |")
    service = results["service"]
    fast_rounds = [v for k, v in service.items() if k.startswith("fast")]
    full_round = next(v for k, v in service.items() if k.startswith("full"))
    lines.append(
        f"| room {results['room_seconds']:g} s | POST /render 320x240 PNG (embedded default) | "
        + " then ".join(f"{r['p50_ms']:.0f} / {r['p95_ms']:.0f} ms" for r in fast_rounds)
        + f" | {full_round['p50_ms']:.0f} / {full_round['p95_ms']:.0f} ms | "
        f"{full_round['p50_ms'] / np.mean([r['p50_ms'] for r in fast_rounds]):.2f}x |"
    )
    lines += ["", "| scene | split | PSNR fast | PSNR full | fast - full |", "| --- | --- | --- | --- | --- |"]
    for scene, r in results["scenes"].items():
        psnr = r["psnr"]
        for split in (k for k in psnr["fast"] if k != "seconds"):
            a, b = psnr["fast"][split], psnr["full"][split]
            lines.append(f"| {scene} | {split} | {a:.3f} dB | {b:.3f} dB | {a - b:+.3f} dB |")
    lines += ["", f"Frame times over {results['poses']} held-out poses per scene, the two paths alternating pose by "
              f"pose; service: {results['renders']} timed renders per round after one warm-up, rounds in the "
              "order fast, full, fast."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--room-seconds", type=float, default=60.0)
    parser.add_argument("--room-long-seconds", type=float, default=0.0,
                        help="also train the room this long in process (0: not)")
    parser.add_argument("--keep-runs", type=Path, help="copy the room and the trained runs here")
    parser.add_argument("--redkitchen", type=Path, help="the 7-Scenes redkitchen scene directory")
    parser.add_argument("--redkitchen-seconds", type=float, default=300.0)
    parser.add_argument("--downscale", type=int, default=2, help="of redkitchen")
    parser.add_argument("--poses", type=int, default=8, help="held-out poses timed in process per scene")
    parser.add_argument("--renders", type=int, default=15, help="timed POST /render per service round")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "render_speed")
    parser.add_argument("--write-docs", action="store_true", help=f"update the results section of {DOC}")
    args = parser.parse_args()
    results: dict = {"environment": {
        "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.system()} {platform.machine()}",
        "cpus": os.cpu_count(), "torch": torch.__version__,
        "load": " ".join(f"{x:.2f}" for x in os.getloadavg()),
    }, "poses": args.poses, "renders": args.renders, "room_seconds": args.room_seconds, "scenes": {}}
    with tempfile.TemporaryDirectory(prefix="voxnerf-render-speed-") as tmp:
        root = Path(tmp)
        room = make_room_scene(root / "room", RoomSpec(width=160, height=120))
        job_id, results["service"] = service_latency(root, root / "data", None, room, args)
        runs = {f"room {args.room_seconds:g} s": (root / "data" / "runs" / job_id, room, 1)}
        if args.room_long_seconds:
            run = root / "room-long-run"
            train(room, run, TrainConfig(max_seconds=args.room_long_seconds, device="cpu"), progress_bar=False)
            runs[f"room {args.room_long_seconds:g} s"] = (run, room, 1)
        if args.redkitchen is not None:
            run = root / "redkitchen-run"
            cfg = TrainConfig(max_seconds=args.redkitchen_seconds, downscale=args.downscale, device="cpu")
            train(args.redkitchen, run, cfg, progress_bar=False)
            runs[f"redkitchen {args.redkitchen_seconds:g} s"] = (run, args.redkitchen, args.downscale)
        for name, (run, scene_dir, downscale) in runs.items():
            print(name, flush=True)
            results["scenes"][name] = {
                "frame_times": frame_times(run, scene_dir, args.poses),
                "psnr": held_out_psnr(run, scene_dir, downscale),
            }
        if args.keep_runs is not None:  # e.g. for the video and mesh examples of docs/outputs.md
            args.keep_runs.mkdir(parents=True, exist_ok=True)
            shutil.copytree(room, args.keep_runs / "room", dirs_exist_ok=True)
            for name, (run, _, _) in runs.items():
                shutil.copytree(run, args.keep_runs / name.replace(" ", "-"), dirs_exist_ok=True)
    command = ".venv/bin/python benchmarks/render_speed.py " + " ".join(sys.argv[1:])
    publish(args.out, results, markdown(results, command.strip()), DOC, SECTION, args.write_docs)


if __name__ == "__main__":
    main()
