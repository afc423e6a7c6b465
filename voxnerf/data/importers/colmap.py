"""``voxnerf import colmap``: a COLMAP sparse model (text or binary) and its images as a docs/scene-format.md scene.

The model is read with pycolmap (``pycolmap.Reconstruction``), from ``DIR/sparse/0``, ``DIR/sparse`` or
``DIR`` itself (the first holding ``cameras.bin`` or ``cameras.txt``); images from ``DIR/images`` unless given.

- Cameras map to transforms.json as nerfstudio's ``colmap_to_json`` maps them: SIMPLE_PINHOLE / PINHOLE ->
  ``PINHOLE``; SIMPLE_RADIAL / RADIAL / OPENCV -> ``OPENCV`` (``k1 k2 p1 p2``, absent terms 0);
  OPENCV_FISHEYE / SIMPLE_RADIAL_FISHEYE / RADIAL_FISHEYE -> ``OPENCV_FISHEYE`` (``k1..k4``); any other model
  is refused naming the camera. COLMAP's principal point is in continuous pixel coordinates (the centre of a
  W x H image is W/2), the convention of this project and of nerfstudio, so ``cx, cy`` are copied unchanged.
  One camera: intrinsics at the top level; several: per frame.
- Poses: COLMAP stores world-to-camera in OpenCV camera axes; frames get camera-to-world in OpenGL axes (camera
  Y and Z flipped). COLMAP's world frame is kept (unlike nerfstudio, no world axes are re-ordered).
- ``points3D`` becomes the prior ``sparse_pc.ply`` (``ply_file_path``, with colours) and ``prior_sigma`` is
  estimated from the points' reprojection errors (:func:`sigma_from_reprojection`). A model without points
  gives a scene without a prior, and the summary says so.
- Frames are sorted by image name (capture order for the usual numbered names); images the model lists but
  the folder lacks are skipped and counted; none left is an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from voxnerf.data.importers import writer
from voxnerf.data.importers.splits import PaperSplitRule, SplitError, split_keys
from voxnerf.errors import SceneError

PLY_NAME = "sparse_pc.ply"
SIGMA_SAMPLE_POINTS = 20_000
"""Points (a fixed random subset of larger models) whose errors estimate ``prior_sigma``."""


def _single_focal(p):
    return p[0], p[0], p[1], p[2]


def _two_focals(p):
    return p[0], p[1], p[2], p[3]


# COLMAP model -> (transforms.json camera_model, params -> (fx, fy, cx, cy), params -> distortion terms)
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": ("PINHOLE", _single_focal, lambda p: {}),
    "PINHOLE": ("PINHOLE", _two_focals, lambda p: {}),
    "SIMPLE_RADIAL": ("OPENCV", _single_focal, lambda p: {"k1": p[3], "k2": 0.0, "p1": 0.0, "p2": 0.0}),
    "RADIAL": ("OPENCV", _single_focal, lambda p: {"k1": p[3], "k2": p[4], "p1": 0.0, "p2": 0.0}),
    "OPENCV": ("OPENCV", _two_focals, lambda p: {"k1": p[4], "k2": p[5], "p1": p[6], "p2": p[7]}),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE", _two_focals, lambda p: {"k1": p[4], "k2": p[5], "k3": p[6], "k4": p[7]}),
    "SIMPLE_RADIAL_FISHEYE": (
        "OPENCV_FISHEYE", _single_focal, lambda p: {"k1": p[3], "k2": 0.0, "k3": 0.0, "k4": 0.0}
    ),
    "RADIAL_FISHEYE": ("OPENCV_FISHEYE", _single_focal, lambda p: {"k1": p[3], "k2": p[4], "k3": 0.0, "k4": 0.0}),
}


@dataclass
class _Model:
    """What the importer takes from a pycolmap Reconstruction."""

    dir: Path
    cameras_file: Path
    recon: object
    frames: list = field(default_factory=list)  # (file_path, source image path, pycolmap Image), by name
    skipped: dict = field(default_factory=dict)


def find_model_dir(src: Path) -> Path:
    """``src/sparse/0``, ``src/sparse`` or ``src``: the first holding cameras.bin or cameras.txt."""
    if not src.is_dir():
        raise SceneError(src, "not a directory")
    for candidate in (src / "sparse" / "0", src / "sparse", src):
        if (candidate / "cameras.bin").is_file() or (candidate / "cameras.txt").is_file():
            return candidate
    raise SceneError(src, "no COLMAP model: cameras.bin or cameras.txt not found in sparse/0, sparse or the folder")


def _read_model(model_dir: Path) -> _Model:
    import pycolmap  # imported here: only an import needs it

    binary = (model_dir / "cameras.bin").is_file()
    cameras_file = model_dir / ("cameras.bin" if binary else "cameras.txt")
    try:
        recon = pycolmap.Reconstruction(str(model_dir))
    except Exception as err:  # pycolmap raises ValueError / RuntimeError for missing or malformed files
        raise SceneError(model_dir, f"cannot read the COLMAP model: {writer.one_line(err)}") from None
    return _Model(model_dir, cameras_file, recon)


def _collect_frames(model: _Model, images_dir: Path) -> None:
    """The model's posed images present in ``images_dir``, sorted by name; the rest counted as skipped."""
    listed = model.cameras_file.with_name("images" + model.cameras_file.suffix)
    images = sorted(model.recon.images.values(), key=lambda im: im.name)
    if not images:
        raise SceneError(listed, "the COLMAP model lists no images")
    for image in images:
        rel = writer.safe_name(image.name, listed)
        src = images_dir / rel
        if not image.has_pose:
            model.skipped["not registered (no pose)"] = model.skipped.get("not registered (no pose)", 0) + 1
        elif not src.is_file():
            model.skipped["image file missing"] = model.skipped.get("image file missing", 0) + 1
        else:
            model.frames.append((f"images/{rel}", src, image))
    if not model.frames:
        raise SceneError(images_dir, f"none of the model's {len(images)} images is here ({model.skipped})")


def camera_entry(camera, cameras_file: Path) -> dict:
    """transforms.json intrinsics (``camera_model``, ``fl_x fl_y cx cy w h`` and distortion) of a COLMAP camera."""
    name = camera.model.name
    if name not in CAMERA_MODELS:
        raise SceneError(
            cameras_file,
            f"camera model {name} is not supported (supported: {', '.join(CAMERA_MODELS)}); undistort the images "
            "with COLMAP's image_undistorter first",
            key=f"camera {camera.camera_id}",
        )
    model_name, focal, distortion = CAMERA_MODELS[name]
    params = [float(v) for v in camera.params]
    fx, fy, cx, cy = focal(params)
    entry = {"camera_model": model_name, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}
    entry.update(w=int(camera.width), h=int(camera.height), **{k: float(v) for k, v in distortion(params).items()})
    return entry


def c2w_opengl(image) -> np.ndarray:
    """Camera-to-world [4, 4] in OpenGL camera axes of a COLMAP image (which stores world-to-camera, OpenCV)."""
    w2c = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
    rot, t = w2c[:3, :3], w2c[:3, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ t
    return c2w @ writer.OPENCV_TO_OPENGL


def _frames_and_cameras(model: _Model) -> tuple[dict, list[dict], list[str]]:
    """Top-level intrinsics (one camera) or {}; the frames; the camera models used (``COLMAP -> ours``)."""
    cam_ids = sorted({image.camera_id for _, _, image in model.frames})
    entries = {cid: camera_entry(model.recon.cameras[cid], model.cameras_file) for cid in cam_ids}
    frames = []
    for file_path, src, image in model.frames:
        entry = entries[image.camera_id]
        writer.check_image(src, entry["w"], entry["h"], f"camera {image.camera_id} of {model.cameras_file.name}")
        frame = {"file_path": file_path, "transform_matrix": writer.pose_list(c2w_opengl(image))}
        frames.append(frame if len(cam_ids) == 1 else {**frame, **entry})
    models = sorted({f"{model.recon.cameras[cid].model.name} -> {entries[cid]['camera_model']}" for cid in cam_ids})
    return (entries[cam_ids[0]] if len(cam_ids) == 1 else {}), frames, models


def sigma_from_reprojection(recon, point_ids: list[int], errors: np.ndarray) -> float | None:
    """``prior_sigma`` (scene units) from the reprojection errors of the points ``point_ids``.

    Rule: a point whose mean reprojection error is ``e`` pixels, seen by a camera at depth ``z`` (along the
    optical axis) with focal length ``f`` pixels, is off by about ``e * z / f`` scene units across that line of
    sight. Per point: ``e`` times the median over its observations of ``z / f``; ``prior_sigma`` is the
    median over points (at most SIGMA_SAMPLE_POINTS of them, a fixed random subset; points without a
    computed error, COLMAP's -1, are left out). It measures lateral error only; depth error along narrow
    baselines is larger, so it is a lower estimate. None when no point has a positive error.
    """
    usable = [(pid, e) for pid, e in zip(point_ids, errors, strict=True) if np.isfinite(e) and e > 0]
    if not usable:
        return None
    if len(usable) > SIGMA_SAMPLE_POINTS:
        pick = np.random.default_rng(0).choice(len(usable), SIGMA_SAMPLE_POINTS, replace=False)
        usable = [usable[i] for i in sorted(pick)]
    depth_rows = _depth_rows(recon)
    per_point = []
    for pid, err in usable:
        point = recon.points3D[pid]
        rows = [depth_rows[el.image_id] for el in point.track.elements if el.image_id in depth_rows]
        ratios = [r for r in ((row[:3] @ point.xyz + row[3]) / row[4] for row in rows) if r > 0]
        if ratios:
            per_point.append(err * float(np.median(ratios)))
    sigma = float(np.median(per_point)) if per_point else 0.0
    return sigma if np.isfinite(sigma) and sigma > 0 else None


def _depth_rows(recon) -> dict[int, np.ndarray]:
    """Per posed image: the world-to-camera matrix's third row (depth = row[:3] @ x + row[3]) and the focal."""
    rows = {}
    for image_id, image in recon.images.items():
        focal = float(image.camera.mean_focal_length()) if image.has_pose else 0.0
        if focal > 0:
            rows[image_id] = np.append(np.asarray(image.cam_from_world().matrix())[2], focal)
    return rows


def _write_prior(root: Path, recon) -> dict:
    """``sparse_pc.ply`` and ``prior_sigma`` from points3D: the transforms.json keys and the summary entry."""
    points = recon.points3D
    if len(points) == 0:
        return {"keys": {}, "summary": None, "note": "the model has no 3D points: no prior written"}
    ids, xyz, rgb, errors = [], [], [], []
    for point_id, point in sorted(points.items(), key=lambda item: item[0]):
        ids.append(point_id)
        xyz.append(point.xyz)
        rgb.append(point.color)
        errors.append(point.error)
    xyz, errors = np.array(xyz, dtype=np.float64), np.array(errors, dtype=np.float64)
    rgb = np.array(rgb, dtype=np.uint8).reshape(-1, 3)
    finite = np.isfinite(xyz).all(axis=1)
    writer.write_points_ply(root / PLY_NAME, xyz[finite], rgb[finite])
    sigma = sigma_from_reprojection(recon, [i for i, ok in zip(ids, finite, strict=True) if ok], errors[finite])
    keys = {"ply_file_path": PLY_NAME, **({"prior_sigma": sigma} if sigma is not None else {})}
    summary = {
        "file": PLY_NAME,
        "points": int(finite.sum()),
        "sigma": sigma,
        "sigma_rule": "median over points of reprojection error (px) x depth / focal (px)"
        if sigma is not None
        else "no reprojection errors in the model: the engine estimates sigma on load",
    }
    return {"keys": keys, "summary": summary, "note": None}


def _fill(root: Path, model: _Model, splits: PaperSplitRule | None, fmt: str = "colmap") -> dict:
    top, frames, models = _frames_and_cameras(model)
    meta = {**top}
    meta["frames"] = frames
    for frame_entry, (_, src, _) in zip(frames, model.frames, strict=True):
        writer.copy_file(src, root / frame_entry["file_path"])
    prior = _write_prior(root, model.recon)
    meta.update(prior["keys"])
    split_summary = None
    if splits is not None:
        try:
            keys, split_summary = split_keys([f["file_path"] for f in frames], splits)
        except SplitError as err:
            raise SceneError(model.dir, str(err), key="--splits paper") from None
        meta.update(keys)
    writer.write_transforms(root, meta)
    return {
        "format": fmt,
        "frames": len(frames),
        "skipped": dict(model.skipped),
        "camera_models": models,
        "depth_frames": 0,
        "prior": prior["summary"],
        "splits": split_summary,
        "notes": [prior["note"]] if prior["note"] else [],
    }


def import_colmap(
    src: str | Path, out: str | Path, splits: PaperSplitRule | None = None, images: str | Path | None = None
) -> dict:
    """Write the COLMAP model under ``src`` as a scene at ``out`` (absent or empty); returns the summary.

    ``images``: the image folder (default ``src/images``); ``splits``: write the paper's splits
    (:mod:`voxnerf.data.importers.splits`), else no split keys. Raises SceneError naming the file at fault; on any
    error nothing is left at ``out``.
    """
    src, out = Path(src), Path(out)
    writer.check_out_dir(out)
    model_dir = find_model_dir(src)
    images_dir = Path(images) if images is not None else src / "images"
    if not images_dir.is_dir():
        raise SceneError(images_dir, "image folder not found (give it with --images)")
    model = _read_model(model_dir)
    _collect_frames(model, images_dir)
    summary = writer.build_scene(out, lambda root: _fill(root, model, splits))
    rel = model_dir.relative_to(src).as_posix() if model_dir != src else "."
    return {**summary, "model": rel}


def import_reconstruction(
    recon, images_dir: Path, out: Path, splits: PaperSplitRule | None, fmt: str, named_in: Path
) -> dict:
    """Write a pycolmap Reconstruction computed in the product (``voxnerf import images | video``) and its images
    in ``images_dir`` as a scene at ``out``, the same way as a model read from disk; ``fmt`` names the importer in
    the summary and ``named_in`` is the file errors name for the model. Nothing is left at ``out`` on error."""
    model = _Model(named_in, named_in, recon)
    _collect_frames(model, images_dir)
    return writer.build_scene(out, lambda root: _fill(root, model, splits, fmt))
