"""What ``voxnerf remote <command>`` does (its flags are defined in :mod:`voxnerf.cli`): each command is one or a
few :class:`~voxnerf.client.api.Client` calls, its result printed on stdout (the id a script wants on the last
line), progress on stderr when it is a terminal. A refusal is one line, the server's ``detail`` (printed by
``voxnerf.cli.main``, exit 2); ``remote train --wait`` exits 1 when the job failed or was cancelled."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from voxnerf.cameras.rules import POSE_FILE_KEYS
from voxnerf.client.api import Client, Event, Progress
from voxnerf.errors import VoxNeRFError


def run_remote(args: argparse.Namespace, job_options: dict | None) -> int:
    """Run ``voxnerf remote <args.remote_command>``; ``job_options``: ``remote train``'s, from its flags."""
    retries = {"retries": args.retries} if hasattr(args, "retries") else {}
    with Client(getattr(args, "url", None), getattr(args, "token", None), **retries) as client:
        if args.remote_command == "train":
            return _train(client, args, job_options or {})
        return COMMANDS[args.remote_command](client, args)


def _progress(label: str) -> Progress | None:
    """A progress line on stderr, rewritten at most 5 times a second, when stderr is a terminal."""
    if not sys.stderr.isatty():
        return None
    last = 0.0

    def show(done: int, total: int | None) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last < 0.2 and done != total:
            return
        last = now
        share = f" {100 * done / total:5.1f} %" if total else ""
        print(f"\r{label}: {done / 2**20:.1f} MiB{share}", end="\n" if done == total else "", file=sys.stderr)

    return show


def _upload(client: Client, args: argparse.Namespace) -> int:
    result = client.upload(args.path, name=args.name, splits=args.splits, progress=_progress("upload"),
                           wait=not args.no_wait)
    if hasattr(result, "layout"):  # --no-wait and a queued import
        print(f"import {result.id} queued ({result.layout}); its scene exists once it has succeeded")
    else:
        print(f"scene {result.name}: {result.summary.frames} frames")
    print(result.id)
    return 0


def _train(client: Client, args: argparse.Namespace, options: dict) -> int:
    job = client.train(args.scene, **options)
    print(job.id, flush=True)
    if not args.wait:
        return 0
    job = client.wait(job.id, on_event=_show_event)
    if job.state == "succeeded":
        for split, metrics in (job.metrics or {}).items():
            if isinstance(metrics, dict) and "psnr" in metrics:
                print(f"{split}: PSNR {metrics['psnr']:.2f} dB")
        print(f"job {job.id} succeeded")
        return 0
    print(f"voxnerf: job {job.id} {job.state}: {job.error or 'no reason given'}", file=sys.stderr)
    return 1


def _show_event(event: Event) -> None:
    """A line on stderr for each state and stage change of a followed job."""
    data = event.data if isinstance(event.data, dict) else {}
    if event.event == "state":
        print(f"state: {data.get('state')} ({100 * (data.get('progress') or 0):.0f} %)", file=sys.stderr)
    elif event.event == "stage" and data.get("name"):
        print(f"stage: {data['name']}", file=sys.stderr)


def _status(client: Client, args: argparse.Namespace) -> int:
    if args.job is None:
        for job in client.jobs(limit=20):
            print(f"{job.id}  {job.state:9}  {100 * job.progress:5.1f} %  scene {job.scene_id}")
        return 0
    job = client.job(args.job)
    if args.json:
        print(job.model_dump_json(indent=2))
        return 0
    eta = f", about {job.eta_s:.0f} s left" if job.eta_s else ""
    print(f"{job.id}: {job.state}, {100 * job.progress:.1f} %{eta} (scene {job.scene_id})")
    if job.error:
        print(f"error: {job.error}")
    for split, metrics in (job.metrics or {}).items():
        if isinstance(metrics, dict) and "psnr" in metrics:
            print(f"{split}: PSNR {metrics['psnr']:.2f} dB")
    return 0


def _read_pose(path: Path) -> dict:
    """A pose file (``voxnerf render --pose``'s keys) as ``POST /render``'s fields; one-line errors naming it."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:
        raise VoxNeRFError(f"{path}: cannot read pose JSON ({exc})") from None
    if not isinstance(data, dict) or "transform_matrix" not in data:
        raise VoxNeRFError(f"{path}: transform_matrix: missing")
    fields = {"transform_matrix": data["transform_matrix"]}
    fields |= {name: data[key] for name, key in POSE_FILE_KEYS.items() if data.get(key) is not None}
    return fields


def _render(client: Client, args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".exr"):
        raise VoxNeRFError(f"--out: {out} must end in .png or .exr")
    size = {"width": args.width, "height": args.height} if args.width or args.height else {}
    pose = _read_pose(Path(args.pose)) if args.pose else None
    client.render(args.job, frame=args.frame, pose=pose, out=out, format=out.suffix.lower()[1:], **size)
    print(out)
    return 0


def _video(client: Client, args: argparse.Namespace) -> int:
    request: dict = {}
    if args.camera_path:
        try:
            request["camera_path"] = json.loads(Path(args.camera_path).read_text())
        except (OSError, ValueError, RecursionError) as exc:
            raise VoxNeRFError(f"{args.camera_path}: cannot read the camera path's JSON ({exc})") from None
    else:
        request["path"] = args.path
    for key in ("frames", "fps", "width", "height", "radius", "height_above"):
        if getattr(args, key) is not None:
            request[key] = getattr(args, key)
    output = client.video(args.job, out=Path(args.out), progress=_progress("download"), **request)
    print(f"video {output.id}: {output.done} frames")
    print(args.out)
    return 0


def _download(client: Client, args: argparse.Namespace) -> int:
    for path in client.download(args.job, args.out, progress=_progress("download")):
        print(path)
    return 0


def _cancel(client: Client, args: argparse.Namespace) -> int:
    job = client.cancel(args.job)
    print(f"job {job.id}: {job.state}{' (cancel requested)' if job.state == 'running' else ''}")
    return 0


COMMANDS = {"upload": _upload, "status": _status, "render": _render, "video": _video, "download": _download,
            "cancel": _cancel}
