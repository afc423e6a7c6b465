"""Training and rendering through the service against ``voxnerf train`` and in-process ``render()``, side by side.

    .venv/bin/python benchmarks/service_speed.py [--seconds 60] [--redkitchen ../shared/data/redkitchen
        --redkitchen-seconds 90 --downscale 2] [--rounds 2] [--renders 5] [--video-frames 12] [--out DIR]
        [--device cpu|cuda] [--room DIR] [--write-docs]

For each scene the same training options go, one after the other on the same idle machine, through ``voxnerf
train`` (a subprocess with the environment the service's processes get), through a job of the real service (uvicorn
+ Celery worker processes on loopback) on its embedded broker, and on a throw-away redis-server; ``--rounds``
times, the order rotated each round, after an untimed two-step ``voxnerf train`` that fills the compile and set-up
caches (so no path pays them cold). Per path: steps, training rays/s (report.json's ``throughput``), PSNR of both
splits and how each process computed (report.json's ``runtime``). With each service's trained job it then measures
rendering: the median of ``POST /render`` 320x240 PNG, that of an 8x6 PNG (whose latency is the service's own
overhead: HTTP, queue, result file), ``render()`` of the same model and pose in this process (after a warm-up), and
a video of ``--video-frames`` frames through the outputs worker (its ``render_seconds``: the first video of the
worker's process, then a second one) against :func:`voxnerf.inference.video.render_path` in this process (after a
warm-up).

Scenes: the 160x120 path-traced room of ``voxnerf synth`` with its transforms.json's ``synthetic`` key removed,
as a user would write it (so pose refinement and per-image appearance train too); with ``--redkitchen``, the
7-Scenes kitchen at ``--downscale``. Results go to ``--out`` (results.json, table.md); ``--write-docs``
replaces the ``service-speed`` section of docs/performance.md.

``--device cuda`` runs every path on the GPU (``voxnerf train --device cuda``, the workers' ``VOXNERF_DEVICE``,
the in-process renders); ``--room DIR`` takes a room made beforehand (``user_room``'s layout) instead of
generating one (a machine without open3d); ``--video-frames 0`` leaves the videos out (a machine without ffmpeg).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers the service tests use

from docs_section import publish  # noqa: E402
from service_fixtures import first_pose, start_redis, start_service, wait_for, zip_scene  # noqa: E402
from service_latency import render_times  # noqa: E402

from voxnerf.cameras import paths as camera_path  # noqa: E402
from voxnerf.cameras.rules import resolve_intrinsics  # noqa: E402
from voxnerf.data.scene import load_scene  # noqa: E402
from voxnerf.inference.render import load_model, render, scene_as_trained  # noqa: E402
from voxnerf.inference.video import render_path  # noqa: E402
from voxnerf.synthetic import RoomSpec, make_room_scene  # noqa: E402

DOC = REPO / "docs" / "performance.md"
SECTION = "service-speed"
RENDER_SIZE = (320, 240)
VIDEO_SIZE = (160, 120)
TRAIN_TIMEOUT_S = 1800


def service_env() -> dict[str, str]:
    """The environment :func:`service_fixtures.start_service` gives the service's processes (VOXNERF_ settings
    aside): ``voxnerf train`` runs in the same one."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    return env | {"PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}


def summary(report: dict, wall_s: float) -> dict:
    """What a path's training gave: steps, rays/s, PSNR per split, its runtime record and stage seconds."""
    return {
        "steps": report["iteration"],
        "rays_per_s": report["throughput"]["rays_per_s"],
        "loop_seconds": report["throughput"]["seconds_excluding_compile"],
        "psnr": {split: m["psnr"] for split, m in (report.get("metrics") or {}).items()},
        "runtime": report.get("runtime"),
        "stages": {s["name"]: round(s["seconds"], 2) for s in report["stages"]},
        "wall_s": wall_s,
    }


def train_cli(scene: Path, run: Path, options: dict, device: str) -> dict:
    """``voxnerf train`` with ``options`` (job option names) on ``device`` in a subprocess; its summary."""
    flags = ["--max-seconds", str(options["max_seconds"]), "--device", device]
    if "downscale" in options:
        flags += ["--downscale", str(options["downscale"])]
    cmd = [sys.executable, "-m", "voxnerf", "train", str(scene), "--out", str(run), *flags]
    started = time.perf_counter()
    done = subprocess.run(cmd, env=service_env(), cwd=REPO, capture_output=True, text=True, timeout=TRAIN_TIMEOUT_S)
    if done.returncode != 0:
        raise RuntimeError(f"voxnerf train failed ({done.returncode}): {done.stderr[-2000:]}")
    return summary(json.loads((run / "report.json").read_text()), time.perf_counter() - started)


def warm_caches(scene: Path, run: Path, options: dict, device: str) -> None:
    """A two-step ``voxnerf train`` with ``options``' downscale and no final evaluation: torch.compile's cache and
    the set-up cache (ray casts) then hold this scene's entries for every path that follows."""
    flags = ["--max-iters", "2", "--device", device, "--set", "final_eval=false"]
    if "downscale" in options:
        flags += ["--downscale", str(options["downscale"])]
    cmd = [sys.executable, "-m", "voxnerf", "train", str(scene), "--out", str(run), *flags]
    done = subprocess.run(cmd, env=service_env(), cwd=REPO, capture_output=True, text=True, timeout=TRAIN_TIMEOUT_S)
    if done.returncode != 0:
        raise RuntimeError(f"the warm-up voxnerf train failed ({done.returncode}): {done.stderr[-2000:]}")


def render_in_process(run_dir: Path, pose: list, count: int, device: str) -> list[float]:
    """Seconds of ``count`` ``render()`` calls of the run's model on ``device`` at ``RENDER_SIZE`` (as POST /render
    resolves the camera), after one untimed warm-up (``render`` returns host arrays: each call ends synchronised)."""
    trained = load_model(run_dir, device)
    intrinsics = resolve_intrinsics(trained.default_intrinsics, width=RENDER_SIZE[0], height=RENDER_SIZE[1])
    c2w = np.asarray(pose)
    render(trained, c2w, intrinsics, ("rgb",))
    times = []
    for _ in range(count):
        started = time.perf_counter()
        render(trained, c2w, intrinsics, ("rgb",))
        times.append(time.perf_counter() - started)
    return times


def video_in_process(run_dir: Path, scene_dir: Path, frames: int, out: Path, device: str) -> float:
    """Seconds :func:`render_path` takes on ``device`` for the ``interpolate`` video the outputs worker makes (same
    path rule), after one untimed video."""
    trained = load_model(run_dir, device)
    scene = scene_as_trained(load_scene(scene_dir, downscale=int(trained.model.config.run.downscale),
                                        load_images=False), trained.model)
    intrinsics = resolve_intrinsics(trained.default_intrinsics, width=VIDEO_SIZE[0],
                                    height=VIDEO_SIZE[1]).undistorted()
    poses = np.stack([scene.frames[i].c2w for i in sorted(scene.train_indices)])
    path = camera_path.generated_path("interpolate", poses, intrinsics, n_frames=frames, fps=30.0)
    render_path(trained, path, out)
    return render_path(trained, path, out).seconds


def video_through_service(client, job_id: str, frames: int) -> float:
    """The outputs worker's ``render_seconds`` for an ``interpolate`` video of ``frames`` frames."""
    body = {"path": "interpolate", "frames": frames, "width": VIDEO_SIZE[0], "height": VIDEO_SIZE[1]}
    response = client.post(f"/jobs/{job_id}/videos", json=body)
    response.raise_for_status()
    output_id = response.json()["id"]
    done = wait_for(lambda: (o := client.get(f"/outputs/{output_id}").json())["state"] in
                    ("succeeded", "failed", "cancelled") and o, 600, "the video", 0.5)
    assert done["state"] == "succeeded", done
    return done["summary"]["render_seconds"]


def through_service(mode: str, root: Path, scene_dir: Path, options: dict, args) -> dict:
    """Train a job with ``options`` through a service on ``mode``'s broker, then time its renders and a video,
    and the same in this process."""
    redis = start_redis(root / f"redis-{mode}") if mode == "redis" else None
    service = start_service(root / mode, broker_url=redis.url if redis else None,
                            settings={"VOXNERF_DEVICE": args.device})
    if args.video_frames:
        service.start_worker("outputs")  # start_service starts the train and render workers
    try:
        with service.client(timeout_s=300) as client:
            scene = client.post("/scenes", files={"file": ("scene.zip", zip_scene(scene_dir), "application/zip")})
            scene.raise_for_status()
            started = time.perf_counter()
            job = client.post(f"/scenes/{scene.json()['id']}/jobs", json=options).json()
            final = wait_for(lambda: (j := client.get(f"/jobs/{job['id']}").json())["state"] in
                             ("succeeded", "failed", "cancelled") and j, TRAIN_TIMEOUT_S, "the job", 1.0)
            wall_s = time.perf_counter() - started
            assert final["state"] == "succeeded", final
            run_dir = next(p.parent for p in service.data_dir.rglob("report.json") if job["id"] in p.as_posix())
            result = summary(json.loads((run_dir / "report.json").read_text()), wall_s)
            pose = first_pose(scene_dir)
            result["render_s"] = render_times(client, job["id"], pose, args.renders, RENDER_SIZE)
            result["overhead_s"] = render_times(client, job["id"], pose, args.renders, (8, 6))
            result["in_process_render_s"] = render_in_process(run_dir, pose, args.renders, args.device)
            if args.video_frames:
                result["video_service_first_s"] = video_through_service(client, job["id"], args.video_frames)
                result["video_service_s"] = video_through_service(client, job["id"], args.video_frames)
                result["video_in_process_s"] = video_in_process(run_dir, scene_dir, args.video_frames,
                                                                root / f"{mode}-video.mp4", args.device)
        return result
    finally:
        service.stop()
        if redis is not None:
            redis.stop()


def user_room(root: Path) -> Path:
    """``voxnerf synth``'s default room, its transforms.json without the ``synthetic`` key."""
    scene = make_room_scene(root / "room", RoomSpec())
    meta = json.loads((scene / "transforms.json").read_text())
    meta.pop("synthetic", None)
    (scene / "transforms.json").write_text(json.dumps(meta, indent=1))
    return scene


def device_name(device: str) -> str:
    """``cpu``, or the CUDA device's name as torch gives it."""
    import torch

    return torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "cpu"


def ms(values: list[float]) -> float:
    return 1000 * statistics.median(values)


PATHS = (("cli", "`voxnerf train`"), ("embedded", "service, embedded"), ("redis", "service, Redis"))


def markdown(results: dict, command: str) -> str:
    env = results["environment"]
    lines = [
        f"Measured {env['date']} on {env['machine']} ({env['cpus']} CPUs, load average {env['load']} at start; "
        f"device {env['device']}), "
        f"each path alone on the machine, {results['rounds']} round(s) in rotated order after a run that fills the "
        "compile and set-up caches. Command:",
        "",
        "```",
        command,
        "```",
        "",
        "Training (report.json: steps of the run, rays/s of its loop less compilation, PSNR of all views; one value "
        "per round; / CLI: the ratio of the medians):",
        "",
        "| scene, settings | path | steps | rays/s | / CLI | PSNR interpolation / extrapolation | OpenMP wait |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for scene in results["scenes"]:
        runs = scene["paths"]
        cli_rate = statistics.median(r["rays_per_s"] for r in runs["cli"])
        for name, label in PATHS:
            rates = [r["rays_per_s"] for r in runs[name]]
            psnr = ", ".join(" / ".join(f"{r['psnr'].get(s, float('nan')):.2f}" for s in ("interpolation",
                                                                                          "extrapolation"))
                             for r in runs[name])
            policies = {(r["runtime"] or {}).get("omp_wait_policy") or "default" for r in runs[name]}
            lines.append(f"| {scene['label']} | {label} | {', '.join(str(r['steps']) for r in runs[name])} | "
                         f"{', '.join(f'{x:,.0f}' for x in rates)} | {statistics.median(rates) / cli_rate:.2f}x | "
                         f"{psnr} | {', '.join(sorted(policies))} |")
    lines += [
        "",
        f"Rendering (medians of {results['renders']} after a warm-up, all rounds pooled; overhead = an 8x6 PNG "
        f"through the service; video: {results['video_frames']} frames at {VIDEO_SIZE[0]}x{VIDEO_SIZE[1]}, render "
        "seconds, the outputs worker's first video and its second, medians over the rounds):",
        "",
        "| scene | service | POST /render 320x240 | overhead | difference | `render()` in process | video, outputs "
        "worker (first / second) | video, in process |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for scene in results["scenes"]:
        for name in ("embedded", "redis"):
            runs = scene["paths"][name]
            post, over, local = (ms([t for r in runs for t in r[key]])
                                 for key in ("render_s", "overhead_s", "in_process_render_s"))
            if results["video_frames"]:
                first, second, here = (statistics.median(r[key] for r in runs)
                                       for key in ("video_service_first_s", "video_service_s", "video_in_process_s"))
                videos = f"{first:.2f} / {second:.2f} s | {here:.2f} s"
            else:
                videos = "not measured | not measured"
            lines.append(f"| {scene['label']} | {name} | {post:.0f} ms | {over:.0f} ms | {post - over:.0f} ms | "
                         f"{local:.0f} ms | {videos} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="max_seconds of the room's runs")
    parser.add_argument("--redkitchen", type=Path, help="the 7-Scenes redkitchen scene directory (added when given)")
    parser.add_argument("--redkitchen-seconds", type=float, default=90.0)
    parser.add_argument("--downscale", type=int, default=2, help="redkitchen's downscale")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each path, in rotated order")
    parser.add_argument("--renders", type=int, default=5, help="timed renders per measurement")
    parser.add_argument("--video-frames", type=int, default=12)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "service_speed")
    parser.add_argument("--device", default="cpu", help="where every path computes: cpu or cuda[:N]")
    parser.add_argument("--room", type=Path, help="a room made beforehand (user_room's layout) instead of a new one")
    parser.add_argument("--write-docs", action="store_true", help=f"replace the {SECTION} section of {DOC}")
    args = parser.parse_args()
    results: dict = {
        "environment": {
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": f"{platform.system()} {platform.machine()}",
            "cpus": os.cpu_count(),
            "load": " ".join(f"{x:.2f}" for x in os.getloadavg()),
            "device": device_name(args.device),
        },
        "rounds": args.rounds,
        "renders": args.renders,
        "video_frames": args.video_frames,
        "scenes": [],
    }
    with tempfile.TemporaryDirectory(prefix="voxnerf-service-speed-") as tmp:
        root = Path(tmp)
        room = args.room if args.room is not None else user_room(root)
        scenes = [(f"path-traced room 160x120, {args.seconds:.0f} s", room, {"max_seconds": args.seconds})]
        if args.redkitchen is not None:
            scenes.append((f"redkitchen 640x480, downscale {args.downscale}, {args.redkitchen_seconds:.0f} s",
                           args.redkitchen, {"max_seconds": args.redkitchen_seconds, "downscale": args.downscale}))
        for index, (label, scene_dir, options) in enumerate(scenes):
            work = root / f"scene{index}"
            warm_caches(scene_dir, work / "warm-up", options, args.device)
            paths: dict[str, list[dict]] = {name: [] for name, _ in PATHS}
            for round_index in range(args.rounds):
                names = [name for name, _ in PATHS]
                for name in names[round_index % 3:] + names[:round_index % 3]:
                    where = work / f"round{round_index}"
                    where.mkdir(parents=True, exist_ok=True)
                    if name == "cli":
                        result = train_cli(scene_dir, where / "cli-run", options, args.device)
                    else:
                        result = through_service(name, where, scene_dir, options, args)
                    paths[name].append(result)
                    print(label, f"round {round_index + 1}", name, json.dumps(result), flush=True)
            results["scenes"].append({"label": label, "options": options, "paths": paths})
            shutil.rmtree(work, ignore_errors=True)
    command = ".venv/bin/python benchmarks/service_speed.py " + " ".join(sys.argv[1:])
    publish(args.out, results, markdown(results, command.strip()), DOC, SECTION, args.write_docs)


if __name__ == "__main__":
    main()
