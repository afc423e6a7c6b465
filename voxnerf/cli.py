"""Command line: ``voxnerf train | eval | render | export | synth | import | serve | worker | tokens | remote``.

Errors the user can fix print one line (``voxnerf: error: <file>: <key>: <message>``) and exit with 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from voxnerf.cameras.rules import POSE_FILE_KEYS, CameraError, Intrinsics, resolve_intrinsics, validate_pose
from voxnerf.errors import RunError, VoxNeRFError

if TYPE_CHECKING:
    from pydantic import ValidationError

    from voxnerf.config import TrainConfig


def _focal_scale(text: str) -> str | float:
    """``--focal-scale``: ``auto`` or a number (TrainConfig checks its range)."""
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto or a number, got {text!r}") from None


def job_option_values(args: argparse.Namespace) -> dict:
    """The training settings of the job-option flags (:func:`_add_job_options`), each ``--set FIELD=VALUE`` (a
    flat name, ``lr``, or a dotted one, ``schedule.lr``) winning over them: ``voxnerf train``'s config less its
    device, and ``voxnerf remote train``'s job options."""
    values = dict(
        preset=args.preset, sampler=args.sampler, max_seconds=args.max_seconds, max_iters=args.max_iters,
        depth_loss=not args.no_depth_loss, depth_source=args.depth_source, downscale=args.downscale,
        pose_refinement=args.pose_refinement, appearance=args.appearance, focal_scale=args.focal_scale,
        seed=args.seed, compile=not args.no_compile, hash_kernel=not args.no_hash_kernel, eval_at=args.eval_at or [],
        **({"eval_every_s": args.eval_every} if args.eval_every else {}),
        **({"n_importance": args.samples[0], "n_rest": args.samples[1]} if args.samples else {}),
        **({"smooth_patches": args.smooth_patches} if args.smooth_patches is not None else {}),
    )
    return values | dict(args.set or [])


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The config of ``voxnerf train``'s flags (:func:`job_option_values` and ``--device``; ``--set device=...``
    wins)."""
    from voxnerf.config import TrainConfig

    return TrainConfig(**({"device": args.device} | job_option_values(args)))


def _train(args: argparse.Namespace) -> int:
    from voxnerf.training.budget import budget_line
    from voxnerf.training.run import train

    config = train_config(args)
    if config.run.max_seconds is None and config.run.max_iters is None:
        raise VoxNeRFError("give --max-seconds or --max-iters (or both)")
    report = train(args.scene, args.out, config, resume=not args.restart)
    for stage in report.stages:
        if stage.name in ("corrections", "weight_decay", "prior", "focal", "depth_target", "octree_carving",
                          "window_check", "colour_prior"):
            print(f"{stage.name}: {stage.why}")
    for warning in report.warnings:
        print(f"warning: {warning}")
    for name, m in (report.metrics or {}).items():
        print(_metrics_line(name, m))
    print(f"{report.status}: {report.iteration} iterations in {report.train_seconds:.1f} s "
          f"({report.throughput['samples_per_s']:.0f} samples/s); report: {Path(args.out) / 'report.json'}")
    print(budget_line(report.budget))
    return 0


def _metrics_line(split: str, m: dict) -> str:
    lp = f"{m['lpips']:.4f}" if m.get("lpips") is not None else m.get("lpips_note", "n/a")
    return f"{split}: PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.4f}  LPIPS {lp}  ({len(m['views'])} views)"


def _eval(args: argparse.Namespace) -> int:
    from voxnerf.data.scene import load_scene
    from voxnerf.inference.evaluation import evaluate_views
    from voxnerf.inference.render import load_model, scene_as_trained
    from voxnerf.training.eval_passes import eval_views_of

    trained = load_model(args.run, args.device)
    scene_dir = args.scene or trained.scene_dir
    if not scene_dir:
        raise RunError(f"{args.run}: the run does not record its scene; pass --scene")
    scene = scene_as_trained(load_scene(scene_dir, downscale=trained.model.config.run.downscale), trained.model)
    split = args.split or ("test" if scene.splits.get("test") else next(iter(scene.eval_split_names), None))
    if split not in scene.splits or split == "train" and not args.split:
        raise RunError(f"{scene_dir}: no evaluation split {split!r} (have {sorted(scene.splits)})")
    views = eval_views_of(scene, trained.model.transform, [split])
    metrics = evaluate_views(trained.model, {split: views[split]}, trained.model.config,
                             out_dir=Path(args.run) / "eval", path=args.render_path)[split]
    print(_metrics_line(split, metrics))
    print(f"rendered by the {metrics['renderer']}")
    if args.json:
        from voxnerf.data.image_io import write_atomic

        payload = {"split": split, **metrics, "iteration": trained.iteration}
        write_atomic(Path(args.json), json.dumps(payload, indent=2).encode())
    return 0


MAX_RENDER_PIXELS = 8192 * 8192


def _read_pose(path: Path, default: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """The pose and camera of a pose file: ``transform_matrix``, optional ``fl_x fl_y cx cy w h`` and an optional
    lens, ``camera_model`` (OPENCV, OPENCV_FISHEYE) with ``k1 k2 k3 k4 p1 p2`` (absent: the pinhole view).

    The rules are :mod:`voxnerf.cameras.rules`' (those of ``POST /render``); a refusal is a RunError
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
    """``voxnerf render``: one image (``--pose``, ``--frame``) or a path (``--camera-path``, ``--path``)."""
    mode = _render_mode(args)
    _check_render_flags(args, mode)
    if mode in ("pose", "frame"):
        return _render_image(args, mode)
    return _render_camera_path(args, mode)


# Flags of `voxnerf render` that only some modes use: flag (argparse dest) -> those modes.
RENDER_FLAG_MODES = {
    "dataparser_transforms": ("camera_path",),
    "frames": ("interpolate", "orbit"),
    "fps": ("interpolate", "orbit"),
    "seconds": ("interpolate", "orbit"),
    "keyframes": ("interpolate",),
    "radius": ("orbit",),
    "height_above": ("orbit",),
    "width": ("interpolate", "orbit", "frame"),
    "height": ("interpolate", "orbit", "frame"),
    "scene": ("interpolate", "orbit", "frame"),
    "with_lens": ("frame",),
    "format": ("camera_path", "interpolate", "orbit"),
}
DEFAULT_PATH_SECONDS = 10.0
DEFAULT_PATH_FPS = 30.0
# Arguments of voxnerf.cameras.paths's functions, by the flag that gives them.
PATH_ARG_FLAGS = {"n_frames": "--frames", "fps": "--fps", "radius": "--radius", "height": "--height-above",
                  "keyframes": "--keyframes",
                  "poses": "the training cameras", "up": "the training cameras' up axes"}


def _render_mode(args: argparse.Namespace) -> str:
    """``pose``, ``frame``, ``camera_path``, ``interpolate`` or ``orbit`` (argparse makes them exclusive)."""
    for mode in ("pose", "frame", "camera_path"):
        if getattr(args, mode) is not None:
            return mode
    return args.path


def _check_render_flags(args: argparse.Namespace, mode: str) -> None:
    for dest, modes in RENDER_FLAG_MODES.items():
        if getattr(args, dest) not in (None, False) and mode not in modes:
            flags = " / ".join("--path " + m if m in ("interpolate", "orbit") else "--" + m.replace("_", "-")
                               for m in modes)
            raise RunError(f"--{dest.replace('_', '-')}: applies to {flags} only")


def _render_image(args: argparse.Namespace, mode: str) -> int:
    from voxnerf.inference.encoding import encode_files, format_of, write_files
    from voxnerf.inference.render import load_model, render

    out = Path(args.out)
    try:
        format_of(out)
    except ValueError:
        raise RunError(f"{out}: output must end in .png or .exr") from None
    trained = load_model(args.run, args.device)
    if mode == "pose":
        pose, intr = _read_pose(Path(args.pose), trained.default_intrinsics)
    else:
        pose, intr = _scene_frame(args, trained)
    outputs = ["rgb"] + (["depth"] if args.depth else []) + (["opacity"] if args.opacity else [])
    images = render(trained, pose, intr, outputs, antialias=args.antialias)
    files = encode_files(out, images, outputs, trained.depth_unit_scale)
    out.parent.mkdir(parents=True, exist_ok=True)
    for path in write_files(files):
        if path != out:
            print(f"wrote {path}")
    print(f"wrote {out} ({intr.width}x{intr.height})")
    return 0


def _run_scene(args: argparse.Namespace, trained):
    """The scene the run trained on (``--scene`` overrides), loaded without its images, its cameras as trained."""
    from voxnerf.data.scene import load_scene
    from voxnerf.inference.render import scene_as_trained

    scene_dir = args.scene or trained.scene_dir
    if not scene_dir:
        raise RunError(f"{args.run}: the run does not record its scene; pass --scene")
    return scene_as_trained(load_scene(scene_dir, load_images=False), trained.model)


def _find_frame(scene, name: str):
    """The frame whose ``file_path``, file name or stem is ``name``; RunError naming ``--frame`` otherwise."""
    matches = [f for f in scene.frames if name in (f.file_path, Path(f.file_path).name, Path(f.file_path).stem)]
    if len(matches) == 1:
        return matches[0]
    where = scene.root / "transforms.json"
    if matches:
        raise RunError(f"--frame: {name!r} names {len(matches)} frames of {where} "
                       f"({', '.join(f.file_path for f in matches[:3])}...): give its file_path")
    examples = ", ".join(f.file_path for f in scene.frames[:3])
    raise RunError(f"--frame: no frame {name!r} in {where} (give a file_path or its stem, e.g. {examples})")


def _sized(args: argparse.Namespace, camera: Intrinsics) -> Intrinsics:
    """``camera`` (lens dropped) scaled to ``--width``/``--height`` by the pose-file rule."""
    try:
        return resolve_intrinsics(camera.undistorted(), width=args.width, height=args.height,
                                  max_pixels=MAX_RENDER_PIXELS)
    except CameraError as err:
        raise RunError(f"--width, --height: {err.message}") from None


def _scene_frame(args: argparse.Namespace, trained) -> tuple[np.ndarray, Intrinsics]:
    """Pose and camera of the scene's frame ``--frame`` at its image size (or ``--width``/``--height``): its
    undistorted pinhole view, or through its lens with ``--with-lens`` (pixel for pixel the captured image)."""
    from dataclasses import replace

    frame = _find_frame(_run_scene(args, trained), args.frame)
    camera = _sized(args, frame.intrinsics)
    return frame.c2w, replace(camera, lens=frame.intrinsics.lens) if args.with_lens else camera


def _frame_count(args: argparse.Namespace) -> tuple[int, float]:
    """Frames and fps of a generated path: ``--frames``, or ``--seconds`` (default 10) at ``--fps`` (30)."""
    from voxnerf.cameras.paths import MAX_FRAMES, check_frame_count
    from voxnerf.cameras.rules import as_finite

    fps = DEFAULT_PATH_FPS if args.fps is None else args.fps
    if args.frames is not None and args.seconds is not None:
        raise RunError("--frames, --seconds: give one of them")
    seconds = DEFAULT_PATH_SECONDS if args.seconds is None else args.seconds
    if as_finite(fps) is None or fps <= 0 or as_finite(seconds) is None or seconds <= 0:
        raise RunError(f"--fps, --seconds: must be positive numbers, got {fps:g} fps, {seconds:g} s")
    total = seconds * fps
    n_frames = args.frames if args.frames is not None else round(total) if total <= MAX_FRAMES else total
    check_frame_count(n_frames, MAX_FRAMES, key="--frames" if args.frames is not None else "--seconds")
    return n_frames, fps


def _training_poses(args: argparse.Namespace, trained) -> np.ndarray:
    """Training cameras ``[K, 4, 4]`` (scene units) in capture order (transforms.json's)."""
    scene = _run_scene(args, trained)
    return np.stack([scene.frames[i].c2w for i in sorted(scene.train_indices)])


def _generated_path(args: argparse.Namespace, mode: str, trained):
    """The ``--path interpolate`` or ``--path orbit`` camera path of the run's training cameras
    (:func:`voxnerf.cameras.paths.generated_path`, the rule of the service's video jobs too)."""
    from voxnerf.cameras.paths import CameraPathError, generated_path

    n_frames, fps = _frame_count(args)
    camera = _sized(args, trained.default_intrinsics)
    try:
        return generated_path(mode, _training_poses(args, trained), camera, n_frames=n_frames, fps=fps,
                              radius=args.radius, height=args.height_above or 0.0, keyframes=args.keyframes)
    except CameraPathError as err:
        raise RunError(f"{PATH_ARG_FLAGS.get(err.key, err.key)}: {err.message}") from None


def _render_camera_path(args: argparse.Namespace, mode: str) -> int:
    """Render ``--camera-path`` or ``--path`` to a video or a frames directory, with a progress bar."""
    from tqdm import tqdm

    from voxnerf.cameras.paths import read_nerfstudio
    from voxnerf.inference.render import load_model
    from voxnerf.inference.video import check_request, format_of, render_path

    out = Path(args.out)
    if out.suffix.lower() in (".png", ".exr"):
        raise RunError(f"{out}: a path renders to VIDEO.mp4 or a frames directory (see --format)")
    fmt = format_of(out, args.format)
    trained = load_model(args.run, args.device)
    if mode == "camera_path":
        transforms = args.dataparser_transforms and Path(args.dataparser_transforms)
        path = read_nerfstudio(Path(args.camera_path), dataparser_transforms=transforms, max_pixels=MAX_RENDER_PIXELS)
    else:
        path = _generated_path(args, mode, trained)
    outputs = ["rgb"] + (["depth"] if args.depth else []) + (["opacity"] if args.opacity else [])
    check_request(path, out, outputs, fmt)
    with tqdm(total=len(path), unit="frame", desc="render", file=sys.stderr) as bar:
        result = render_path(trained, path, out, outputs=outputs, fmt=fmt,
                             on_frame=lambda done, total: bar.update(done - bar.n), antialias=args.antialias)
    width, height = path.size
    print(f"wrote {result.out} ({result.frames} frames, {width}x{height}, {path.fps:g} fps) in "
          f"{result.seconds:.1f} s")
    print(f"wrote {result.path_file}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from voxnerf.data.scene import load_scene
    from voxnerf.inference.export import export_geometry
    from voxnerf.inference.render import load_model, scene_as_trained

    targets = [(kind, path) for kind, path in (("mesh", args.mesh), ("pointcloud", args.pointcloud)) if path]
    if not targets:
        raise RunError("give --mesh OUT.ply or --pointcloud OUT.ply (or both)")
    trained = load_model(args.run, args.device)
    scene = None
    if args.scene:
        scene = scene_as_trained(load_scene(args.scene, downscale=int(trained.model.config.run.downscale),
                                            load_images=False), trained.model)
    elif not trained.scene_dir:
        raise RunError(f"{args.run}: the run does not record its scene; pass --scene")
    for kind, path in targets:
        result = export_geometry(trained, Path(path), kind, scene=scene, voxel_size=args.voxel_size,
                                 min_opacity=args.min_opacity, max_views=args.max_views,
                                 on_view=_progress_line(kind))
        print(f"wrote {result.out}: {result.points} {'vertices' if kind == 'mesh' else 'points'}, "
              f"{result.faces} faces, voxel {result.voxel_size:.4g}, {result.views} views, {result.seconds:.1f} s")
    return 0


def _progress_line(label: str):
    """on_view callback drawing ``label: done/total views`` on one stderr line."""

    def on_view(done: int, total: int) -> None:
        print(f"\r{label}: {done}/{total} views", end="\n" if done == total else "", file=sys.stderr, flush=True)

    return on_view


def _synth(args: argparse.Namespace) -> int:
    from voxnerf.synthetic import RoomSpec, make_room_scene

    spec = RoomSpec(width=args.width, height=args.height, n_frames=args.frames, prior_kind=args.prior,
                    prior_sigma=args.sigma, seed=args.seed)
    try:
        make_room_scene(Path(args.out), spec)
    except ValueError as err:  # a spec the room's camera path or splits cannot be made from
        raise VoxNeRFError(f"voxnerf synth --frames {args.frames}: {err}") from None
    print(f"wrote {args.out}")
    return 0


def _import(args: argparse.Namespace) -> int:
    from voxnerf.data.importers import PaperSplitRule, describe, import_colmap, import_scannet

    splits = PaperSplitRule() if args.splits == "paper" else None
    if args.layout == "colmap":
        summary = import_colmap(args.dir, args.out, splits, images=args.images)
    elif args.layout in PHONE_APP_LAYOUTS:
        summary = _import_phone_app(args, splits)
    elif args.layout == "images":
        from voxnerf.data.importers.sfm import import_images

        summary = import_images(args.dir, args.out, splits, matching=args.matching)
    elif args.layout == "video":
        from voxnerf.data.importers.video import import_video

        summary = import_video(args.file, args.out, splits=splits,
                               **({"n_frames": args.frames} if hasattr(args, "frames") else {}))
    else:
        summary = import_scannet(args.dir, args.out, splits)
    for line in describe(summary):
        print(line)
    print(f"wrote {args.out}")
    return 0


def _import_rosbag(args: argparse.Namespace) -> int:
    from voxnerf.data.importers import PaperSplitRule, RosbagOptions, describe, import_rosbag

    given = {name: getattr(args, name) for name in ("min_translation", "min_rotation", "sync_tolerance")
             if hasattr(args, name)}
    options = RosbagOptions(rgb=args.rgb, depth=args.depth, camera_info=args.camera_info,
                            fixed_frame=args.fixed_frame, pose_topic=args.pose_topic, pose_frame=args.pose_frame,
                            all_frames=args.all_frames, **given)
    summary = import_rosbag(args.bag, args.out, PaperSplitRule() if args.splits == "paper" else None, options)
    for line in describe(summary):
        print(line)
    print(f"wrote {args.out}")
    return 0
PHONE_APP_LAYOUTS = ("record3d", "polycam", "stray")


def _import_phone_app(args: argparse.Namespace, splits) -> dict:
    """``voxnerf import record3d|polycam|stray``: a LiDAR phone app's export, its depth kept."""
    if args.layout == "record3d":
        from voxnerf.data.importers.record3d import import_record3d

        return import_record3d(args.dir, args.out, splits, every=args.every)
    if args.layout == "polycam":
        from voxnerf.data.importers.polycam import import_polycam

        return import_polycam(args.dir, args.out, splits, min_confidence=args.min_confidence)
    from voxnerf.data.importers.stray import import_stray

    return import_stray(args.dir, args.out, splits, min_confidence=args.min_confidence, every=args.every)


def _at_least_one(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _serve(args: argparse.Namespace) -> int:
    from app.serve import serve

    serve(args.host, args.port)
    return 0


def _tokens(args: argparse.Namespace) -> int:
    from app.tokens_cli import run

    return run(args)


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


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (np.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return value


def _sample_counts(text: str) -> tuple[int, int]:
    try:
        n_imp, n_rest = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N_IMP,N_REST (two integers), got {text!r}") from None
    if n_imp < 1 or n_rest < 1:
        raise argparse.ArgumentTypeError(f"sample counts must be positive, got {text!r}")
    return n_imp, n_rest


def _config_setting(text: str) -> tuple[str, object]:
    """``FIELD=VALUE`` -> (field, value): VALUE as JSON where it parses, else the text itself."""
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
    try:
        return name.strip(), json.loads(value)
    except json.JSONDecodeError:
        return name.strip(), value


def _add_train_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a model on a scene directory")
    p.add_argument("scene", help="scene directory (transforms.json and its files; see docs/scene-format.md)")
    p.add_argument("--out", required=True, help="run directory (checkpoint, report.json, eval renders)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    _add_job_options(p)
    p.set_defaults(func=_train)


def _add_job_options(p: argparse.ArgumentParser) -> None:
    """The training flags a job takes, locally (``voxnerf train``) or on a service (``voxnerf remote train``,
    ``POST /scenes/{id}/jobs``): read by :func:`job_option_values`."""
    p.add_argument("--max-seconds", type=float, help="seconds of training (set-up, compilation and the final "
                   "evaluation come on top: docs/engine.md, 'The time budget')")
    p.add_argument("--max-iters", type=int)
    p.add_argument("--sampler", choices=["auto", "voxnerf", "occgrid", "uniform"], default="auto",
                   help="auto: the VoxNeRF sampler unless the set-up finds the prior's first hits wrong on more than "
                   "6 %% of the rays with depth, then the occupancy grid (report.json says which and why)")
    p.add_argument("--no-depth-loss", action="store_true", help="leave the depth terms out (as --depth-source none)")
    p.add_argument("--depth-source", choices=["auto", "sensor", "prior", "none"], default="auto",
                   help="what the depth loss compares with: the training frames' depth maps (the prior's depth "
                   "where they have none), the prior's depth, or nothing; auto: sensor when the training frames "
                   "have depth maps, else prior when there is one")
    p.add_argument("--pose-refinement", choices=["auto", "none", "so3xr3"], default="auto",
                   help="so3xr3: learn a rotation and translation per training image (scans whose poses drift, "
                   "e.g. from SLAM or COLMAP); rendered poses take their nearest training cameras' corrections; the "
                   "refined poses go to refined_poses.json (docs/engine.md); auto: so3xr3 unless transforms.json "
                   "says the scene is synthetic")
    p.add_argument("--appearance", choices=["auto", "none", "affine"], default="auto",
                   help="affine: learn a colour gain and bias per training image (auto-exposure, white balance); "
                   "a rendered view takes its nearest training cameras' correction (docs/engine.md); auto: affine "
                   "unless transforms.json says the scene is synthetic")
    p.add_argument("--focal-scale", type=_focal_scale, default="auto", metavar="auto|SCALE",
                   help="the colour camera's focal lengths are the stated ones times SCALE (1: as stated); auto: "
                   "measured on a captured scan with a mesh prior, from how well the training images agree through "
                   "the prior (docs/engine.md)")
    p.add_argument("--preset", choices=["cpu", "paper"], default="cpu")
    p.add_argument("--downscale", type=int, default=1)
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
    p.add_argument("--set", type=_config_setting, action="append", metavar="FIELD=VALUE",
                   help="any training-config setting (docs/engine.md lists them), by its name or its dotted name "
                   "in its component, e.g. --set lr_schedule=budget --set model.sh_bands=2; VALUE is read as JSON "
                   "where it parses (numbers, true, [1, 2]), else as text; "
                   "repeatable, and it wins over the flags above")


def _add_eval_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluate a run on a held-out split")
    p.add_argument("run")
    p.add_argument("--split", help="split name (default: test, or the first evaluation split)")
    p.add_argument("--scene", help="scene directory (default: the one the run trained on)")
    p.add_argument("--json", help="write the metrics here")
    p.add_argument("--device", default="auto")
    p.add_argument("--render-path", choices=["auto", "fast", "full"], default="auto",
                   help="fast: rays stop when opaque, no compiling; full: every sample of every ray; auto "
                        "(default): fast on the CPU, full on a GPU")
    p.set_defaults(func=_eval)


def _add_render_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="render a pose, a scene frame or a camera path (PNG, EXR, MP4 or a frames directory)",
        description="Render one image (--pose, --frame) to IMG.png or IMG.exr, or a camera path (--camera-path, "
        "--path) to VIDEO.mp4 (H.264) or a frames directory (frame_00000.png ..., with camera_path.json). "
        "Poses are in the scene's units; see docs/engine.md, 'Camera paths and video'.")
    p.add_argument("run", help="run directory (its checkpoint.pt)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--pose", help="JSON with transform_matrix and optional fl_x fl_y cx cy, w h (together)")
    what.add_argument("--frame", metavar="NAME",
                      help="the scene's own camera NAME (a frame's file_path or its stem), undistorted")
    what.add_argument("--camera-path", metavar="PATH.json",
                      help="a nerfstudio camera path (its viewer's Render export): camera_path[] with "
                      "camera_to_world and fov, render_width, render_height, fps, seconds")
    what.add_argument("--path", choices=["interpolate", "orbit"],
                      help="interpolate: through the training cameras in capture order; orbit: around their "
                      "centre, looking at it")
    p.add_argument("--out", required=True, help="IMG.png | IMG.exr (--pose, --frame); VIDEO.mp4 or a frames "
                   "directory, absent or empty (--camera-path, --path)")
    p.add_argument("--depth", action="store_true",
                   help="also render depth (EXR channel Z, or IMG_depth.png / frame_00000_depth.png, 16-bit)")
    p.add_argument("--opacity", action="store_true",
                   help="also render opacity (EXR channel A, or IMG_opacity.png as 8-bit gray)")
    p.add_argument("--format", choices=["png", "exr"], help="files of a frames directory (default png)")
    p.add_argument("--no-antialias", dest="antialias", action="store_false", default=None,
                   help="render each pixel's colour from its centre ray alone: a fifth of the rays of the "
                   "antialiased default (the run's antialias setting, docs/engine.md)")
    p.add_argument("--dataparser-transforms", metavar="FILE",
                   help="--camera-path: the nerfstudio run's dataparser_transforms.json, mapping the viewer's "
                   "poses back to the scene's units")
    p.add_argument("--scene", help="scene directory (default: the one the run trained on) for --frame and --path")
    p.add_argument("--with-lens", action="store_true",
                   help="--frame: render through the frame's lens distortion, as the camera captured it")
    p.add_argument("--frames", type=int, help="--path: number of frames (default: --seconds x --fps)")
    p.add_argument("--seconds", type=float, help=f"--path: duration (default {DEFAULT_PATH_SECONDS:g})")
    p.add_argument("--fps", type=float, help=f"--path: frames per second (default {DEFAULT_PATH_FPS:g})")
    p.add_argument("--keyframes", type=int, metavar="N",
                   help="--path interpolate: through N training cameras evenly spaced in capture order "
                        "(default: one per 8 frames, all when the path is long enough)")
    p.add_argument("--width", type=int, help="--path, --frame: image width (with --height; default the run's camera)")
    p.add_argument("--height", type=int, help="--path, --frame: image height (with --width)")
    p.add_argument("--radius", type=float,
                   help="--path orbit: radius in scene units (default: the cameras' mean distance from their centre)")
    p.add_argument("--height-above", type=float, metavar="Z",
                   help="--path orbit: height of the circle above the centre along the cameras' up (default 0)")
    p.add_argument("--device", default="auto")
    p.set_defaults(func=_render)


def _add_export_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export the run's geometry as a coloured mesh and/or point cloud (PLY)",
                       description="Render the run from its training cameras (and small offsets of them) and "
                       "write a TSDF mesh and/or a point cloud in the scene's coordinates and units; see "
                       "docs/engine.md, Geometry export.")
    p.add_argument("run")
    p.add_argument("--mesh", metavar="OUT.ply", help="write the TSDF mesh (vertex colours) here")
    p.add_argument("--pointcloud", metavar="OUT.ply", help="write the point cloud (colours, normals) here")
    p.add_argument("--scene", help="scene directory (default: the one the run trained on)")
    p.add_argument("--voxel-size", type=float, metavar="M",
                   help="voxel / point spacing in scene units (default: the scene box's longest side / 512)")
    p.add_argument("--min-opacity", type=float, default=0.5,
                   help="pixels rendering less opaque than this carry no surface (default 0.5)")
    p.add_argument("--max-views", type=int, metavar="N", help="render at most N views (default: all)")
    p.add_argument("--device", default="auto")
    p.set_defaults(func=_export)


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
    p = sub.add_parser("import", help="write a COLMAP model, a ScanNet export, a LiDAR phone app's export, a "
                       "ROS bag, photos or a video as a scene (docs/scene-format.md)",
                       description="Write a COLMAP sparse model, a ScanNet export, a Record3D / Polycam / Stray "
                       "Scanner export, a robot's ROS bag, or photos or a video without poses (posed by structure "
                       "from motion) as a scene in the project's format; see "
                       "docs/scene-format.md.")
    layouts = p.add_subparsers(dest="layout", required=True)
    colmap = layouts.add_parser("colmap", help="a COLMAP sparse model (sparse/0, sparse or DIR; text or binary)")
    colmap.add_argument("--images", help="the image folder (default DIR/images)")
    scannet = layouts.add_parser("scannet", help="ScanNet's exported color/ depth/ pose/ intrinsic/ folders")
    record3d = layouts.add_parser("record3d", help="Record3D's EXR + JPG export (EXR_RGBD: metadata.json, rgb/, "
                                  "depth/), LiDAR depth kept")
    polycam = layouts.add_parser("polycam", help="Polycam's raw-data export (keyframes/ with images, cameras, depth, "
                                 "confidence), LiDAR depth kept")
    stray = layouts.add_parser("stray", help="a Stray Scanner recording (rgb.mp4, odometry.csv, camera_matrix.csv, "
                               "depth/, confidence/), LiDAR depth kept")
    for q in (polycam, stray):
        q.add_argument("--min-confidence", choices=["low", "medium", "high"], default="medium",
                       help="drop depth ARKit graded below this (default medium; low keeps all)")
    for q in (record3d, stray):
        q.add_argument("--every", type=_at_least_one, default=1, metavar="N",
                       help="keep every N-th frame (the apps record up to 60 per second; default 1: all)")
    # The SfM flags' defaults live in voxnerf.data.importers.sfm / .video (absent here, so that building the parser
    # does not load the importers); tests/data/test_import_images.py checks that the help states them.
    images = layouts.add_parser("images", help="a folder of photos without poses, posed by structure from motion")
    images.add_argument("--matching", choices=["auto", "exhaustive", "sequential"], default="auto",
                        help="image pairs to match: auto (exhaustive up to 60 photos, else sequential in name "
                        "order), exhaustive or sequential")
    video = layouts.add_parser("video", help="a video (MP4/MOV, H.264/HEVC) without poses: the sharpest frames, "
                               "posed by structure from motion")
    video.add_argument("file", metavar="FILE")
    video.add_argument("--frames", type=int, default=argparse.SUPPRESS, metavar="N",
                       help="frames to keep: the sharpest of each of N equal time windows (default 100)")
    for q in (colmap, scannet, record3d, polycam, stray, images):
        q.add_argument("dir", metavar="DIR")
    for q in (colmap, scannet, record3d, polycam, stray, images, video):
        q.add_argument("--out", required=True, metavar="SCENE", help="scene directory to write (absent or empty)")
        q.add_argument("--splits", choices=["paper"],
                       help="write the paper's train / interpolation / extrapolation splits (default: none)")
        q.set_defaults(func=_import)
    _add_import_rosbag(layouts)


def _add_import_rosbag(layouts: argparse._SubParsersAction) -> None:
    # The numeric flags default to RosbagOptions' values (absent here, so that building the parser does not load
    # the importers); tests/data/test_import_rosbag.py checks that the help states those values.
    q = layouts.add_parser("rosbag", help="a robot's ROS 1 .bag or ROS 2 bag (sqlite3 or MCAP): colour, depth, "
                           "CameraInfo and poses from /tf or a pose topic")
    q.add_argument("bag", metavar="BAG", help="a ROS 1 .bag file, a ROS 2 bag folder, or its .db3 / .mcap file")
    q.add_argument("--out", required=True, metavar="SCENE", help="scene directory to write (absent or empty)")
    q.add_argument("--rgb", metavar="TOPIC", help="the colour Image or CompressedImage topic (default: the only one)")
    q.add_argument("--depth", metavar="TOPIC", help="the depth Image topic, 16UC1 mm or 32FC1 m (default: the only "
                   "one); 'none' imports colour only")
    q.add_argument("--camera-info", metavar="TOPIC", help="the colour camera's CameraInfo topic (default: the one "
                   "beside the colour topic, or the only one)")
    q.add_argument("--fixed-frame", metavar="FRAME", help="the world frame of the scene (default: the root of the "
                   "camera frame's transform tree)")
    q.add_argument("--pose-topic", metavar="TOPIC", help="poses from this PoseStamped / PoseWithCovarianceStamped / "
                   "Odometry / TransformStamped topic instead of /tf")
    q.add_argument("--pose-frame", metavar="FRAME", help="the frame a PoseStamped's pose is of (default: the "
                   "camera's frame); linked to the camera by the transforms")
    q.add_argument("--all-frames", action="store_true", help="keep every posed frame (default: keep a frame when "
                   "the camera moved --min-translation or turned --min-rotation since the last kept one)")
    q.add_argument("--min-translation", type=_non_negative, default=argparse.SUPPRESS, metavar="M",
                   help="metres (default 0.05)")
    q.add_argument("--min-rotation", type=_non_negative, default=argparse.SUPPRESS, metavar="DEG",
                   help="degrees (default 5)")
    q.add_argument("--sync-tolerance", type=_non_negative, default=argparse.SUPPRESS, metavar="S",
                   help="seconds between a colour image and the depth image it takes (default 0.02)")
    q.add_argument("--splits", choices=["paper"],
                   help="write the paper's train / interpolation / extrapolation splits (default: none)")
    q.set_defaults(func=_import_rosbag)


def _add_serve_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="start the REST API with an embedded worker")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.set_defaults(func=_serve)


def _add_worker_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="start a Celery worker")
    p.add_argument("--queues", default="train,render,outputs")
    p.add_argument("--concurrency", type=int, default=1)
    p.set_defaults(func=_worker)


def _add_tokens_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tokens", help="named API tokens of the service (on the database voxnerf serve would use)")
    actions = p.add_subparsers(dest="tokens_command", required=True)
    q = actions.add_parser("create", help="make a token; prints it on the last line, once")
    q.add_argument("name", help="a slug: lowercase letters, digits, '-' and '_'")
    q.add_argument("--scope", required=True, choices=["read", "write", "admin"],
                   help="read: GET only; write: upload, train, render, outputs, cancel and delete its own work; "
                   "admin: everything, tokens included")
    q.add_argument("--max-queued", type=_at_least_one, default=None,
                   help="queued rows of each kind it may have (default VOXNERF_MAX_QUEUED_PER_TOKEN)")
    actions.add_parser("list", help="every token, revoked ones included (never the token itself)")
    q = actions.add_parser("revoke", help="revoke a token: refused from the service's next request")
    q.add_argument("name")
    q = actions.add_parser("show-secret", help="print a token's webhook secret (hex)")
    q.add_argument("name")
    p.set_defaults(func=_tokens)


def _remote(args: argparse.Namespace) -> int:
    from voxnerf.client.commands import run_remote

    options = None
    if args.remote_command == "train":
        options = job_option_values(args) | ({"callback_url": args.callback_url} if args.callback_url else {})
    return run_remote(args, options)


def _add_remote_command(sub: argparse._SubParsersAction) -> None:
    """``voxnerf remote ...``: the same work on a running service (voxnerf.client; docs/service.md)."""
    p = sub.add_parser("remote", help="work with a running VoxNeRF service: upload, train, status, render, video, "
                       "download, cancel", description="Talk to a VoxNeRF service (voxnerf serve) at --url or "
                       "VOXNERF_URL (default http://127.0.0.1:8000), with --token or VOXNERF_API_TOKEN.")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--url", default=argparse.SUPPRESS, help="the service (default: VOXNERF_URL)")
    common.add_argument("--token", default=argparse.SUPPRESS, help="its API token (default: VOXNERF_API_TOKEN)")
    common.add_argument("--retries", type=_non_negative_int, default=argparse.SUPPRESS,
                        help="attempts after the first on 429, 503 and connection errors, with back-off (default 6)")
    commands = p.add_subparsers(dest="remote_command", required=True)
    _add_remote_work(commands, common)
    _add_remote_views(commands, common)
    p.set_defaults(func=_remote)


def _add_remote_work(commands: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """``voxnerf remote upload | train | status | cancel``."""
    q = commands.add_parser("upload", parents=[common], help="upload a scene directory, zip or capture; the last "
                            "line printed is the new scene's id")
    q.add_argument("path", help="a scene directory (zipped first), a .zip, or a capture (video, ROS bag...)")
    q.add_argument("--name", help="display name (default: the file or directory name)")
    q.add_argument("--splits", choices=["paper"], help="an upload to import: write the paper's splits")
    q.add_argument("--no-wait", action="store_true",
                   help="a capture whose import is queued: print the import's id instead of waiting for its scene")
    q = commands.add_parser("train", parents=[common], help="train a scene on the service; prints the job id")
    q.add_argument("scene", help="the scene's id")
    q.add_argument("--wait", action="store_true",
                   help="follow the job until it ends: exit 0 when it succeeded, 1 when it failed or was cancelled")
    q.add_argument("--callback-url", metavar="URL", help="where the service posts the job's state changes, signed "
                   "(webhooks: docs/service.md)")
    _add_job_options(q)
    q = commands.add_parser("status", parents=[common], help="a job's state and progress, or the latest jobs")
    q.add_argument("job", nargs="?", help="a job id (default: list the latest jobs)")
    q.add_argument("--json", action="store_true", help="print the job as GET /jobs/{id} answers it")
    q = commands.add_parser("cancel", parents=[common], help="cancel a queued or running job")
    q.add_argument("job")


def _add_remote_views(commands: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """``voxnerf remote render | video | download``."""
    q = commands.add_parser("render", parents=[common], help="render a view of a finished job to PNG or EXR")
    q.add_argument("job")
    view = q.add_mutually_exclusive_group(required=True)
    view.add_argument("--frame", metavar="NAME", help="the scene's camera NAME (a frame's file_path or its stem)")
    view.add_argument("--pose", metavar="FILE", help="JSON with transform_matrix and optional fl_x fl_y cx cy, w h "
                      "and a lens, as voxnerf render --pose")
    q.add_argument("--out", required=True, help="IMG.png or IMG.exr (EXR: colour, depth and opacity)")
    q.add_argument("--width", type=int, help="image width (with --height; default the camera's)")
    q.add_argument("--height", type=int)
    q = commands.add_parser("video", parents=[common], help="render a fly-through video (MP4) of a finished job")
    q.add_argument("job")
    path = q.add_mutually_exclusive_group(required=True)
    path.add_argument("--path", choices=["interpolate", "orbit"], help="a path generated from the training cameras")
    path.add_argument("--camera-path", metavar="FILE.json", help="a nerfstudio camera path")
    q.add_argument("--frames", type=int, help="--path: number of frames")
    q.add_argument("--fps", type=float, help="--path: frames per second (default 30)")
    q.add_argument("--width", type=int, help="--path: frame width (with --height; default the scene's)")
    q.add_argument("--height", type=int)
    q.add_argument("--radius", type=float, help="--path orbit: radius, scene units")
    q.add_argument("--height-above", type=float, help="--path orbit: height above the cameras' centre")
    q.add_argument("--out", required=True, help="VIDEO.mp4")
    q = commands.add_parser("download", parents=[common], help="download a finished job's run: report.json, "
                            "checkpoint.pt, evaluation renders, output files")
    q.add_argument("job")
    q.add_argument("--out", required=True, help="directory to write into (voxnerf render reads it as a run)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="voxnerf", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    _add_train_command(sub)
    _add_eval_command(sub)
    _add_render_command(sub)
    _add_export_command(sub)
    _add_synth_command(sub)
    _add_import_command(sub)
    _add_serve_command(sub)
    _add_worker_command(sub)
    _add_tokens_command(sub)
    _add_remote_command(sub)
    return parser


def validation_message(exc: ValidationError) -> str:
    """One line for the first field a pydantic ``ValidationError`` names: its path without pydantic's tags for
    the branches of a union ('constrained-float', "literal['auto']"), and what each branch would have taken."""
    errors = exc.errors()
    path = _field_path(errors[0]["loc"])
    messages = dict.fromkeys(e["msg"] for e in errors if _field_path(e["loc"]) == path)
    return f"{path}: " + ", or ".join(m if i == 0 else m[:1].lower() + m[1:] for i, m in enumerate(messages))


def _field_path(loc: tuple) -> str:
    """``loc`` as a dotted path of field names and list indices; a union branch's tag is neither. A training
    setting is named by its flat name (``sh_bands``, not ``model.sh_bands``), as the flags and ``--set`` name it."""
    from voxnerf.config import SECTIONS

    if len(loc) >= 2 and loc[0] in SECTIONS and loc[1] in SECTIONS[loc[0]].model_fields:
        loc = loc[1:]
    return ".".join(str(part) for part in loc
                    if isinstance(part, int) or all(name.isidentifier() for name in str(part).split(".")))


def main(argv: list[str] | None = None) -> int:
    from pydantic import ValidationError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValidationError as exc:
        print(f"voxnerf: error: {validation_message(exc)}", file=sys.stderr)
        return 2
    except VoxNeRFError as exc:
        print(f"voxnerf: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("voxnerf: interrupted", file=sys.stderr)
        return 130
