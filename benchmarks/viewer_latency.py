"""The viewer's latency after a drag: from the drag's last move to the first frame of the final pose on screen
(the 1/4-size frame, or the full one when the camera was already at rest), and to the full-size frame.

    .venv/bin/python benchmarks/viewer_latency.py [--room-seconds 60] [--size 320x240] [--drags 20]
        [--out DIR] [--write-docs]

A synthetic room of ``--size`` pixels is uploaded to the real service on its embedded default (uvicorn,
filesystem queue, SQLite, one train and one render worker) and trained there for ``--room-seconds``. Debian's
chromium (headless, through playwright) opens the job's viewer and makes ``--drags`` scripted mouse drags,
each followed by a wait for the full frame; the times are the page's own (``performance.now()`` when the
camera last moved and when each frame was drawn). Results go to ``--out`` (results.json, table.md;
default benchmarks/results/viewer_latency/); ``--write-docs`` puts the table into docs/viewer.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the process helpers the service tests use

from docs_section import publish  # noqa: E402
from service_fixtures import start_service, wait_for, zip_scene  # noqa: E402

from voxnerf.synthetic import RoomSpec, make_room_scene  # noqa: E402

DOC = REPO / "docs" / "viewer.md"
SECTION = "viewer-latency"
CHROMIUM = "/usr/bin/chromium"
TARGET_MS = 150  # the small frame's target after a drag
SETTLED = """() => { const s = window.viewerState; return s && s.frames.shownQuality === "full" && !s.frames.inflight
  && s.frames.shownKey === s.currentKey(); }"""
# The page's times of the last drag: when the camera last moved, and when frames of the final view were drawn.
LAST_DRAG = """() => { const s = window.viewerState, key = s.currentKey();
  const shown = s.frames.log.filter((f) => f.key === key);
  return { movedAt: s.frames.lastMoveAt, first: shown[0], full: shown.find((f) => f.quality === "full") }; }"""
# Request to screen of every frame the page drew (the log keeps the last 500), by size.
ROUND_TRIPS = """() => window.viewerState.frames.log.map((f) => [f.quality, f.shownAt - f.requestedAt])"""


def percentiles(ms: list[float]) -> dict:
    values = np.asarray(ms)
    return {"n": len(values), "p50_ms": float(np.percentile(values, 50)), "p95_ms": float(np.percentile(values, 95)),
            "max_ms": float(values.max())}


def trained_job(service, room: Path, seconds: float) -> str:
    """A job trained for ``seconds`` on ``room`` through the service; its id."""
    with service.client() as client:
        scene = client.post("/scenes", files={"file": ("room.zip", zip_scene(room), "application/zip")}).json()
        job = client.post(f"/scenes/{scene['id']}/jobs", json={"max_seconds": seconds}).json()
        wait_for(lambda: client.get(f"/jobs/{job['id']}").json()["state"] in ("succeeded", "failed", "cancelled"),
                 seconds + 900, "the job to finish", 2.0)
        state = client.get(f"/jobs/{job['id']}").json()["state"]
        if state != "succeeded":
            raise RuntimeError(f"the job ended {state}:\n{service.logs()}")
    return job["id"]


def drag(page, dx: float, dy: float, steps: int) -> None:
    """A mouse drag from the stage's centre, ``steps`` moves of ~16 ms (a 60 Hz hand)."""
    box = page.locator("#stage").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for i in range(1, steps + 1):
        page.mouse.move(x + dx * i / steps, y + dy * i / steps)
        page.wait_for_timeout(16)
    page.mouse.up()


def measure(base_url: str, job_id: str, drags: int) -> dict:
    """Latencies (ms) of ``drags`` scripted drags in the viewer of ``job_id``."""
    from playwright.sync_api import sync_playwright

    first, full, small_first = [], [], 0
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": 1300, "height": 850})
            page.goto(f"{base_url}/static/viewer.html?job={job_id}")
            page.wait_for_function(SETTLED, timeout=120_000)
            for i in range(drags):
                angle = 2 * np.pi * i / max(1, drags)
                drag(page, 90 * np.cos(angle), 30 * np.sin(angle), steps=12)
                page.wait_for_function(SETTLED, timeout=120_000)
                times = page.evaluate(LAST_DRAG)
                first.append(times["first"]["shownAt"] - times["movedAt"])
                full.append(times["full"]["shownAt"] - times["movedAt"])
                small_first += times["first"]["quality"] == "small"
                page.wait_for_timeout(300)
            trips = page.evaluate(ROUND_TRIPS)
        finally:
            browser.close()
    return {"first_frame": percentiles(first), "full_frame": percentiles(full), "small_first": small_first,
            "drags": drags, "round_trip": {quality: percentiles([ms for q, ms in trips if q == quality])
                                           for quality in ("small", "full")}}


def markdown(results: dict, command: str) -> str:
    env, r = results["environment"], results["latency"]
    first, full = r["first_frame"], r["full_frame"]
    return "\n".join([
        f"Measured {env['date']} on {env['machine']} ({env['cpus']} CPUs, load {env['load']} at start), the "
        f"embedded default, a {results['size']} room trained {results['room_seconds']:g} s; "
        f"{r['drags']} scripted drags. Command:", "", "```", command, "```", "",
        "| from the end of a drag to | p50 | p95 | max |", "| --- | --- | --- | --- |",
        f"| the first frame of the final pose | {first['p50_ms']:.0f} ms | {first['p95_ms']:.0f} ms | "
        f"{first['max_ms']:.0f} ms |",
        f"| its full-size frame | {full['p50_ms']:.0f} ms | {full['p95_ms']:.0f} ms | {full['max_ms']:.0f} ms |",
        *(f"| (one {quality} frame, request to screen, {trip['n']} frames) | {trip['p50_ms']:.0f} ms | "
          f"{trip['p95_ms']:.0f} ms | {trip['max_ms']:.0f} ms |" for quality, trip in r["round_trip"].items()),
        "", f"The first frame was the 1/4-size one after {r['small_first']} of {r['drags']} drags (otherwise the "
        f"camera had rested 200 ms before the frame in flight came back, and the full frame came first). "
        f"Target for the small frame: {TARGET_MS} ms.",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--room-seconds", type=float, default=60.0)
    parser.add_argument("--size", default="320x240", help="the room's image size, WIDTHxHEIGHT")
    parser.add_argument("--drags", type=int, default=20)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "viewer_latency")
    parser.add_argument("--write-docs", action="store_true", help=f"update the results section of {DOC}")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    results: dict = {"environment": {
        "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.system()} {platform.machine()}",
        "cpus": os.cpu_count(), "load": " ".join(f"{x:.2f}" for x in os.getloadavg()),
    }, "room_seconds": args.room_seconds, "size": f"{width}x{height}"}
    with tempfile.TemporaryDirectory(prefix="voxnerf-viewer-latency-") as tmp:
        root = Path(tmp)
        room = make_room_scene(root / "room", RoomSpec(width=width, height=height))
        service = start_service(root / "service")
        try:
            job_id = trained_job(service, room, args.room_seconds)
            results["latency"] = measure(service.base_url, job_id, args.drags)
        finally:
            service.stop()
    command = ".venv/bin/python benchmarks/viewer_latency.py " + " ".join(sys.argv[1:])
    publish(args.out, results, markdown(results, command.strip()), DOC, SECTION, args.write_docs)


if __name__ == "__main__":
    main()
