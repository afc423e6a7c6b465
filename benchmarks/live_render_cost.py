"""What viewing a job while it trains costs its training: the same job through the service, alone and viewed.

    .venv/bin/python benchmarks/live_render_cost.py [--seconds 150] [--rounds 1] [--interval 0] [--size 96 72]
        [--checkpoint-every 5] [--out DIR]

One real service (uvicorn + Celery train and render workers on its embedded broker) trains the same job options on
a synthetic 96x72 room of 40 frames, ``--rounds`` times each way, the order alternated: *alone* (nobody renders)
and *viewed* (from its first checkpoint on, a client renders a held-out pose at ``--size`` with ``POST /render``
back to back, or one every ``--interval`` seconds: a viewer whose user keeps moving is the worst case, 0). A
checkpoint every ``--checkpoint-every`` seconds, so the viewed job's renders load several checkpoints. An untimed
two-step job first fills the set-up caches. Per job: steps, training rays/s (report.json's ``throughput``), and
for the viewed one the renders made, their median latency and the checkpoints they came from. Results go to ``--out``
(results.json, table.md).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers the service tests use

from service_fixtures import first_pose, start_service, wait_for, zip_scene  # noqa: E402

from voxnerf.synthetic import RoomSpec, make_room_scene  # noqa: E402

ROOM = RoomSpec(width=96, height=72, n_frames=40, train_every=4, n_gaps=0, gap_len=0, prior_max_points=50_000)
TIMEOUT_S = 1800


class Viewer(threading.Thread):
    """Renders ``body`` through ``client``'s service from the job's first checkpoint until stopped; records each
    render's seconds and the iteration that made it."""

    def __init__(self, service, job_id: str, body: dict, interval_s: float) -> None:
        super().__init__(daemon=True)
        self.service, self.job_id, self.body, self.interval_s = service, job_id, body, interval_s
        self.stop = threading.Event()
        self.renders: list[tuple[float, int]] = []

    def run(self) -> None:
        with self.service.client() as client:
            while not self.stop.is_set():
                started = time.perf_counter()
                response = client.post("/render", json=self.body)
                if response.status_code == 200:
                    self.renders.append((time.perf_counter() - started, int(response.headers["X-VoxNeRF-Iteration"])))
                    self.stop.wait(self.interval_s)
                else:  # 409 before the first checkpoint, or once the job ended
                    self.stop.wait(0.5)


def train(service, scene_id: str, options: dict, viewer_body: dict | None, interval_s: float) -> dict:
    """One job with ``options``; viewed by a :class:`Viewer` when ``viewer_body`` is given. Its summary."""
    with service.client() as client:
        job_id = client.post(f"/scenes/{scene_id}/jobs", json=options).json()["id"]
        viewer = None
        if viewer_body is not None:
            viewer = Viewer(service, job_id, {**viewer_body, "job_id": job_id}, interval_s)
            viewer.start()
        started = time.perf_counter()
        row = wait_for(lambda: (j := client.get(f"/jobs/{job_id}").json())["state"] in (
            "succeeded", "failed", "cancelled") and j, TIMEOUT_S, f"job {job_id} to finish", 1.0)
        wall = time.perf_counter() - started
        if viewer is not None:
            viewer.stop.set()
            viewer.join(120)
        if row["state"] != "succeeded":
            raise RuntimeError(f"job {job_id} ended {row['state']}: {row['error']}\n{service.logs()}")
        report = client.get(f"/jobs/{job_id}/report").json()
    result = {"job": job_id, "steps": report["iteration"], "rays_per_s": report["throughput"]["rays_per_s"],
              "loop_seconds": report["throughput"]["seconds_excluding_compile"], "wall_s": wall}
    if viewer is not None:
        seconds = [s for s, _ in viewer.renders]
        result |= {"renders": len(seconds), "render_median_ms": 1000 * statistics.median(seconds) if seconds else None,
                   "checkpoints_rendered": sorted({i for _, i in viewer.renders})}
    return result


def markdown(results: dict, command: str) -> str:
    lines = [f"`{command}` on {results['machine']} ({results['cpus']} cores), {results['when']}.", "",
             "| round | how | steps | training rays/s | renders | median render (ms) | checkpoints rendered |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for run in results["runs"]:
        renders = median = checkpoints = "–"
        if run["how"] == "viewed":
            renders = str(run["renders"])
            median = "–" if run["render_median_ms"] is None else f"{run['render_median_ms']:.0f}"
            checkpoints = ", ".join(map(str, run["checkpoints_rendered"])) or "–"
        lines.append(f"| {run['round']} | {run['how']} | {run['steps']} | {run['rays_per_s']:,.0f} | {renders} | "
                     f"{median} | {checkpoints} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=150.0, help="max_seconds of each job")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--interval", type=float, default=0.0, help="seconds between the viewer's renders")
    parser.add_argument("--size", type=int, nargs=2, default=(96, 72), metavar=("W", "H"))
    parser.add_argument("--checkpoint-every", type=float, default=5.0)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "live_viewer")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="live-render-cost-") as tmp:
        root = Path(tmp)
        room = make_room_scene(root / "room", ROOM)
        service = start_service(root / "service", settings={"VOXNERF_CHECKPOINT_EVERY_S": str(args.checkpoint_every)})
        try:
            with service.client() as client:
                scene_id = client.post("/scenes", files={"file": ("room.zip", zip_scene(room), "application/zip")},
                                       ).json()["id"]
            options = {"max_seconds": args.seconds, "compile": False}
            train(service, scene_id, {"max_iters": 2, "compile": False}, None, 0)  # fills the set-up caches
            body = {"transform_matrix": first_pose(room), "width": args.size[0], "height": args.size[1]}
            runs = []
            for round_ in range(1, args.rounds + 1):
                order = ("alone", "viewed") if round_ % 2 else ("viewed", "alone")
                for how in order:
                    run = train(service, scene_id, options, body if how == "viewed" else None, args.interval)
                    runs.append({"round": round_, "how": how, **run})
                    print(json.dumps(runs[-1]), flush=True)
        finally:
            service.stop()
    results = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
               "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "args": vars(args) | {"out": str(args.out)},
               "runs": runs}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    (args.out / "table.md").write_text(markdown(results, " ".join(["benchmarks/live_render_cost.py", *sys.argv[1:]])))
    print(markdown(results, "benchmarks/live_render_cost.py"))


if __name__ == "__main__":
    main()
