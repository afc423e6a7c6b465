"""Command line: ``voxnerf train | eval | render | synth | import | serve | worker``.

Errors the user can fix print one line (``voxnerf: error: <file>: <key>: <message>``) and exit with 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from voxnerf.camera_rules import LENS_KEYS, CameraError, Intrinsics, resolve_intrinsics, validate_pose
from voxnerf.errors import RunError, VoxNeRFError


def _train(args: argparse.Namespace) -> int:
    from voxnerf.config import TrainConfig
    from voxnerf.training.run import train

    config = TrainConfig(
        preset=args.preset, sampler=args.sampler, max_seconds=args.max_seconds, max_iters=args.max_iters,
        depth_loss=not args.no_depth_loss, depth_source=args.depth_source, downscale=args.downscale,
        device=args.device, seed=args.seed,
        compile=not args.no_compile, hash_kernel=not args.no_hash_kernel, eval_at=args.eval_at or [],
        **({"eval_every_s": args.eval_every} if args.eval_every else {}),
        **({"n_importance": args.samples[0], "n_rest": args.samples[1]} if args.samples else {}),
        **({"smooth_patches": args.smooth_patches} if args.smooth_patches is not None else {}),
    )
    if config.max_seconds is None and config.max_iters is None:
        raise VoxNeRFError("give --max-seconds or --max-iters (or both)")
    report = train(args.scene, args.out, config, resume=not args.restart)
    for stage in report.stages:
        if stage.name in ("prior", "depth_target"):
            print(f"{stage.name}: {stage.why}")
    for warning in report.warnings:
        print(f"warning: {warning}")
    for name, m in (report.metrics or {}).items():
        print(_metrics_line(name, m))
    print(f"{report.status}: {report.iteration} iterations in {report.train_seconds:.1f} s "
          f"({report.throughput['samples_per_s']:.0f} samples/s); report: {Path(args.out) / 'report.json'}")
    return 0


def _metrics_line(split: str, m: dict) -> str:
    lp = f"{m['lpips']:.4f}" if m.get("lpips") is not None else m.get("lpips_note", "n/a")
    return f"{split}: PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.4f}  LPIPS {lp}  ({len(m['views'])} views)"


def _eval(args: argparse.Namespace) -> int:
    from voxnerf.evaluation import evaluate_views
    from voxnerf.render import load_model
    from voxnerf.scene import load_scene
    from voxnerf.training.evals import eval_views_of

    trained = load_model(args.run, args.device)
    scene_dir = args.scene or trained.scene_dir
    if not scene_dir:
        raise RunError(f"{args.run}: the run does not record its scene; pass --scene")
    scene = load_scene(scene_dir, downscale=trained.model.config.downscale)
    split = args.split or ("test" if scene.splits.get("test") else next(iter(scene.eval_split_names), None))
    if split not in scene.splits or split == "train" and not args.split:
        raise RunError(f"{scene_dir}: no evaluation split {split!r} (have {sorted(scene.splits)})")
    views = eval_views_of(scene, trained.model.transform, [split])
    metrics = evaluate_views(trained.model, {split: views[split]}, trained.model.config,
                             out_dir=Path(args.run) / "eval")[split]
    print(_metrics_line(split, metrics))
    if args.json:
        from voxnerf.image_io import write_atomic

        payload = {"split": split, **metrics, "iteration": trained.iteration}
        write_atomic(Path(args.json), json.dumps(payload, indent=2).encode())
    return 0


MAX_RENDER_PIXELS = 8192 * 8192
# Pose-file keys of the intrinsics and the lens, by resolve_intrinsics' argument name.
POSE_FILE_KEYS = {"fl_x": "fl_x", "fl_y": "fl_y", "cx": "cx", "cy": "cy", "width": "w", "height": "h",
                  **{key: key for key in LENS_KEYS}}


def _read_pose(path: Path, default: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """The pose and camera of a pose file: ``transform_matrix``, optional ``fl_x fl_y cx cy w h`` and an optional
    lens, ``camera_model`` (OPENCV, OPENCV_FISHEYE) with ``k1 k2 k3 k4 p1 p2`` (absent: the pinhole view).

    The rules are :mod:`voxnerf.camera_rules`' (those of ``POST /render``); a refusal is a RunError
    ``FILE: KEY: why``.
    """
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad UTF-8 or JSON
        raise RunError(f"{path}: cannot read pose JSON ({exc})") from None
    if not isinstance(data, dict) or "transform_matrix" not in data:
        raise RunError(f"{path}: transform_matrix: missing")
    try:
        pose = validate_pose(data["transform_matrix"])
    except CameraError as err:
        raise RunError(f"{path}: transform_matrix: {err}") from None
    given = {arg: data.get(key) for arg, key in POSE_FILE_KEYS.items()}
    try:
        intrinsics = resolve_intrinsics(default, **given, max_pixels=MAX_RENDER_PIXELS)
    except CameraError as err:
        field = ", ".join(POSE_FILE_KEYS.get(name, name) for name in (err.field or "").split(", "))
        raise RunError(f"{path}: {field}: {err.message}") from None
    return pose, intrinsics


def _render(args: argparse.Namespace) -> int:
    from voxnerf.outputs import encode_files, format_of, write_files
    from voxnerf.render import load_model, render

    out = Path(args.out)
    try:
        format_of(out)
    except ValueError:
        raise RunError(f"{out}: output must end in .png or .exr") from None
    trained = load_model(args.run, args.device)
    pose, intr = _read_pose(Path(args.pose), trained.default_intrinsics)
    outputs = ["rgb"] + (["depth"] if args.depth else []) + (["opacity"] if args.opacity else [])
    images = render(trained, pose, intr, outputs)
    files = encode_files(out, images, outputs, trained.depth_unit_scale)
    out.parent.mkdir(parents=True, exist_ok=True)
    for path in write_files(files):
        if path != out:
            print(f"wrote {path}")
    print(f"wrote {out} ({intr.width}x{intr.height})")
    return 0


def _synth(args: argparse.Namespace) -> int:
    from voxnerf.synthetic import RoomSpec, make_room_scene

    spec = RoomSpec(width=args.width, height=args.height, n_frames=args.frames, prior_kind=args.prior,
                    prior_sigma=args.sigma, seed=args.seed)
    make_room_scene(Path(args.out), spec)
    print(f"wrote {args.out}")
    return 0


def _import(args: argparse.Namespace) -> int:
    from voxnerf.importers import PaperSplitRule, describe, import_colmap, import_scannet

    splits = PaperSplitRule() if args.splits == "paper" else None
    if args.layout == "colmap":
        summary = import_colmap(args.dir, args.out, splits, images=args.images)
    else:
        summary = import_scannet(args.dir, args.out, splits)
    for line in describe(summary):
        print(line)
    print(f"wrote {args.out}")
    return 0


def _serve(args: argparse.Namespace) -> int:
    from app.serve import serve

    serve(args.host, args.port)
    return 0


def _worker(args: argparse.Namespace) -> int:
    from worker.run import run_worker

    run_worker([q for q in args.queues.split(",") if q], args.concurrency)
    return 0


def _seconds_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated seconds, got {text!r}") from None
    return values


def _sample_counts(text: str) -> tuple[int, int]:
    try:
        n_imp, n_rest = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N_IMP,N_REST (two integers), got {text!r}") from None
    if n_imp < 1 or n_rest < 1:
        raise argparse.ArgumentTypeError(f"sample counts must be positive, got {text!r}")
    return n_imp, n_rest


def _add_train_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a model on a scene directory")
    p.add_argument("scene", help="scene directory (transforms.json and its files; see docs/scene-format.md)")
    p.add_argument("--out", required=True, help="run directory (checkpoint, report.json, eval renders)")
    p.add_argument("--max-seconds", type=float, help="wall-clock bound of the whole command")
    p.add_argument("--max-iters", type=int)
    p.add_argument("--sampler", choices=["voxnerf", "occgrid", "uniform"], default="voxnerf")
    p.add_argument("--no-depth-loss", action="store_true", help="leave the depth terms out (as --depth-source none)")
    p.add_argument("--depth-source", choices=["auto", "sensor", "prior", "none"], default="auto",
                   help="what the depth loss compares with: the training frames' depth maps (the prior's depth "
                   "where they have none), the prior's depth, or nothing; auto: sensor when the training frames "
                   "have depth maps, else prior when there is one")
    p.add_argument("--preset", choices=["cpu", "paper"], default="cpu")
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-compile", action="store_true", help="run the training step eagerly")
    p.add_argument("--no-hash-kernel", action="store_true",
                   help="keep the hash encoding in pure PyTorch on the CPU (default: its C kernel where it builds)")
    p.add_argument("--eval-at", type=_seconds_list,
                   help="full evaluations at these training seconds, e.g. 120,300 (for benchmarks: their time is "
                   "not charged to --max-seconds)")
    p.add_argument("--eval-every", type=float, metavar="SECONDS",
                   help="training seconds between progress evaluations of a few views (default 60)")
    p.add_argument("--samples", type=_sample_counts, metavar="N_IMP,N_REST",
                   help="samples per ray near the surface and on the rest of the ray (default: the preset's)")
    p.add_argument("--smooth-patches", type=int, metavar="N",
                   help="add the paper's depth-smoothness term on N 8x8 patches per batch (default 0: off)")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    p.set_defaults(func=_train)


def _add_eval_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluate a run on a held-out split")
    p.add_argument("run")
    p.add_argument("--split", help="split name (default: test, or the first evaluation split)")
    p.add_argument("--scene", help="scene directory (default: the one the run trained on)")
    p.add_argument("--json", help="write the metrics here")
    p.add_argument("--device", default="auto")
    p.set_defaults(func=_eval)


def _add_render_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render a camera pose to PNG or EXR")
    p.add_argument("run")
    p.add_argument("--pose", required=True,
                   help="JSON with transform_matrix and optional fl_x fl_y cx cy, w h (together)")
    p.add_argument("--out", required=True, help="IMG.png or IMG.exr")
    p.add_argument("--depth", action="store_true", help="also render depth (EXR channel Z, or IMG_depth.png)")
    p.add_argument("--opacity", action="store_true",
                   help="also render opacity (EXR channel A, or IMG_opacity.png as 8-bit gray)")
    p.add_argument("--device", default="auto")
    p.set_defaults(func=_render)


def _add_synth_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("synth", help="generate a synthetic furnished-room scene")
    p.add_argument("out")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--prior", choices=["points", "mesh", "none"], default="points")
    p.add_argument("--sigma", type=float, default=0.02)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_synth)


def _add_import_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import", help="write a COLMAP model or a ScanNet export as a scene (docs/scene-format.md)",
                       description="Write a COLMAP sparse model or a ScanNet export as a scene in the project's "
                       "format; see docs/scene-format.md.")
    layouts = p.add_subparsers(dest="layout", required=True)
    colmap = layouts.add_parser("colmap", help="a COLMAP sparse model (sparse/0, sparse or DIR; text or binary)")
    colmap.add_argument("--images", help="the image folder (default DIR/images)")
    scannet = layouts.add_parser("scannet", help="ScanNet's exported color/ depth/ pose/ intrinsic/ folders")
    for q in (colmap, scannet):
        q.add_argument("dir", metavar="DIR")
        q.add_argument("--out", required=True, metavar="SCENE", help="scene directory to write (absent or empty)")
        q.add_argument("--splits", choices=["paper"],
                       help="write the paper's train / interpolation / extrapolation splits (default: none)")
        q.set_defaults(func=_import)


def _add_serve_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="start the REST API with an embedded worker")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.set_defaults(func=_serve)


def _add_worker_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="start a Celery worker")
    p.add_argument("--queues", default="train,render")
    p.add_argument("--concurrency", type=int, default=1)
    p.set_defaults(func=_worker)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="voxnerf", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    _add_train_command(sub)
    _add_eval_command(sub)
    _add_render_command(sub)
    _add_synth_command(sub)
    _add_import_command(sub)
    _add_serve_command(sub)
    _add_worker_command(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from pydantic import ValidationError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValidationError as exc:
        first = exc.errors()[0]
        print(f"voxnerf: error: {'.'.join(map(str, first['loc']))}: {first['msg']}", file=sys.stderr)
        return 2
    except VoxNeRFError as exc:
        print(f"voxnerf: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("voxnerf: interrupted", file=sys.stderr)
        return 130
