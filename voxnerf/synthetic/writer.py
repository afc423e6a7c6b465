"""Writing the room as a docs/scene-format.md scene: transforms.json, sRGB and depth PNGs, the prior and true mesh."""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh

from voxnerf.camera_rules import COEFFICIENT_KEYS, MODEL_COEFFICIENTS, CameraError, Lens, lens_of
from voxnerf.image_io import build_dir_atomic
from voxnerf.synthetic.cameras import FrameSplits, camera_path, split_frames
from voxnerf.synthetic.geometry import RoomGeometry
from voxnerf.synthetic.priors import PRIOR_KINDS, noisy_mesh_prior, sample_point_prior
from voxnerf.synthetic.raycast import render_view
from voxnerf.synthetic.room import build_room

HORIZONTAL_FOV_DEG = 65.0
DEPTH_UNIT_SCALE = 0.001
"""Metres per unit of the 16-bit depth PNGs (millimetres)."""


@dataclass
class RoomSpec:
    """What :func:`make_room_scene` writes. Defaults give the 5 x 4 x 2.6 m room at 160 x 120 pixels."""

    width: int = 160
    height: int = 120
    n_frames: int = 160
    train_every: int = 10
    n_gaps: int = 2
    gap_len: int = 30
    prior_kind: str = "points"
    prior_sigma: float = 0.02
    prior_max_points: int = 300_000
    write_depth: bool = True
    supersample: int = 2
    seed: int = 0
    hfov_deg: float = HORIZONTAL_FOV_DEG
    lens: dict | None = None
    """A lens to render through, as transforms.json gives it: ``{"camera_model": "OPENCV", "k1": ...}``
    (``OPENCV`` or ``OPENCV_FISHEYE`` with nerfstudio's coefficient names); None: a pinhole."""

    def camera_lens(self) -> Lens | None:
        """:attr:`lens` as a :class:`Lens`; ValueError naming the bad key."""
        if self.lens is None:
            return None
        if not isinstance(self.lens, dict) or set(self.lens) - {"camera_model", *COEFFICIENT_KEYS}:
            raise ValueError(f"RoomSpec.lens must hold camera_model and k1 k2 k3 k4 p1 p2 only, got {self.lens!r}")
        try:
            return lens_of(self.lens.get("camera_model"), self.lens)
        except CameraError as err:
            raise ValueError(f"RoomSpec.lens: {err}") from None

    def validate(self) -> None:
        """ValueError naming the first bad field."""
        for name in ("width", "height", "n_frames", "train_every", "supersample", "prior_max_points"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"RoomSpec.{name} must be a positive integer, got {getattr(self, name)!r}")
        if self.prior_kind not in PRIOR_KINDS:
            raise ValueError(f"RoomSpec.prior_kind must be one of {PRIOR_KINDS}, got {self.prior_kind!r}")
        if not (math.isfinite(self.prior_sigma) and self.prior_sigma > 0):
            raise ValueError(
                f"RoomSpec.prior_sigma must be a positive number of metres, got {self.prior_sigma!r}"
            )
        if not 10.0 <= self.hfov_deg <= 120.0:
            raise ValueError(f"RoomSpec.hfov_deg must be in [10, 120], got {self.hfov_deg!r}")
        self.camera_lens()


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, image, extension=".png")


def _check_out_dir(out_dir: Path) -> None:
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir}: output must not exist or be an empty directory")


def make_room_scene(out_dir: Path, spec: RoomSpec | None = None) -> Path:
    """Render the synthetic room into ``out_dir`` (which must not exist or be empty); returns ``out_dir``.

    Writes ``transforms.json``, ``images/frame-NNNNNN.png`` (sRGB), ``depth/frame-NNNNNN.png`` (16-bit mm) for
    the frames some split uses, ``prior.ply`` (unless ``prior_kind == "none"``) and ``gt_mesh.ply``. The whole
    directory is built beside ``out_dir`` and renamed into place, so a partial scene is never visible.
    Same spec -> byte-identical files.
    """
    spec = spec or RoomSpec()
    spec.validate()
    out_dir = Path(out_dir)
    _check_out_dir(out_dir)
    splits = split_frames(spec.n_frames, spec.train_every, spec.n_gaps, spec.gap_len)
    build_dir_atomic(out_dir, lambda tmp: _write_scene(tmp, spec, splits), _check_out_dir)
    return out_dir



def _write_scene(root: Path, spec: RoomSpec, splits: FrameSplits) -> None:
    geom = build_room(spec.seed)
    w, h = spec.width, spec.height
    fl = (w / 2) / math.tan(math.radians(spec.hfov_deg) / 2)
    meta: dict = {"camera_model": "PINHOLE", "fl_x": fl, "fl_y": fl, "cx": w / 2, "cy": h / 2, "w": w, "h": h}
    lens = spec.camera_lens()
    if lens is not None:  # nerfstudio's keys: the model and every coefficient it has
        meta["camera_model"] = lens.model
        meta.update({key: getattr(lens, key) for key in MODEL_COEFFICIENTS[lens.model]})
    if spec.write_depth:
        meta["depth_unit_scale_factor"] = DEPTH_UNIT_SCALE
    meta["frames"] = _write_frames(root, spec, geom, splits.used, fl)
    meta.update(_split_lists(splits))
    prior_info = _write_prior(root, spec, geom)
    if prior_info is not None:
        meta["prior_file_path"] = "prior.ply"
        meta["prior_sigma"] = spec.prior_sigma
    geom.to_trimesh().export(root / "gt_mesh.ply")
    meta["voxnerf_synthetic"] = _generator_record(spec, splits, geom, prior_info)
    (root / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")


def _write_frames(root: Path, spec: RoomSpec, geom: RoomGeometry, indices: list[int], fl: float) -> list[dict]:
    """Render and write the frames ``indices`` of the camera path; their transforms.json ``frames`` entries."""
    poses = camera_path(spec.n_frames)
    w, h = spec.width, spec.height
    frames = []
    for i in indices:
        name = f"frame-{i:06d}.png"
        rgb, depth = render_view(geom, poses[i], fl, w / 2, h / 2, w, h, spec.supersample, spec.camera_lens())
        _write_png(root / "images" / name, np.round(rgb * 255).astype(np.uint8))
        frame = {"file_path": f"images/{name}", "transform_matrix": np.round(poses[i], 8).tolist()}
        if spec.write_depth:
            depth_units = np.clip(np.round(depth / DEPTH_UNIT_SCALE), 0, 65535).astype(np.uint16)
            _write_png(root / "depth" / name, depth_units)
            frame["depth_file_path"] = f"depth/{name}"
        frames.append(frame)
    return frames


def _split_lists(splits: FrameSplits) -> dict:
    """The transforms.json keys naming each split's image paths."""

    def paths(indices: list[int]) -> list[str]:
        return [f"images/frame-{i:06d}.png" for i in indices]

    lists: dict = {
        "train_filenames": paths(splits.train),
        "test_filenames": paths(splits.interpolation),
        "eval_splits": {"interpolation": paths(splits.interpolation)},
    }
    if splits.extrapolation:
        lists["eval_splits"]["extrapolation"] = paths(splits.extrapolation)
    return lists


def _write_prior(root: Path, spec: RoomSpec, geom: RoomGeometry) -> dict | None:
    """Write ``prior.ply`` of ``spec.prior_kind``; its description, None for ``"none"``."""
    rng = np.random.default_rng([spec.seed, 1])
    if spec.prior_kind == "points":
        points, prior_info = sample_point_prior(geom, spec.prior_sigma, spec.prior_max_points, rng)
        trimesh.PointCloud(points).export(root / "prior.ply")
        return prior_info
    if spec.prior_kind == "mesh":
        mesh, prior_info = noisy_mesh_prior(geom, spec.prior_sigma, rng)
        mesh.export(root / "prior.ply")
        return prior_info
    return None


def _spec_record(spec: RoomSpec) -> dict:
    """``asdict(spec)``, without ``lens`` when there is none (so a pinhole scene's files stay as they were)."""
    record = asdict(spec)
    if record["lens"] is None:
        del record["lens"]
    return record


def _generator_record(spec: RoomSpec, splits: FrameSplits, geom: RoomGeometry, prior_info: dict | None) -> dict:
    """transforms.json ``voxnerf_synthetic``: how the scene was made and where its objects are."""
    return {
        "seed": spec.seed,
        "room_size": list(geom.room_size),
        "world_up": [0.0, 0.0, 1.0],
        "spec": _spec_record(spec),
        "gt_mesh_file_path": "gt_mesh.ply",
        "prior": prior_info,
        "split_frame_indices": asdict(splits),
        "lights": [asdict(light) for light in geom.lights],
        "objects": {
            o.name: {"pattern": o.material.pattern, "bounds": [list(o.bounds[0]), list(o.bounds[1])]}
            for o in geom.objects
        },
    }


def main(argv: list[str] | None = None) -> None:
    """``python -m voxnerf.synthetic OUT_DIR [SEED]``: write the default scene and print what it holds."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (1, 2):
        raise SystemExit("usage: python -m voxnerf.synthetic OUT_DIR [SEED]")
    spec = RoomSpec(seed=int(args[1]) if len(args) == 2 else 0)
    start = time.perf_counter()
    out = make_room_scene(Path(args[0]), spec)
    meta = json.loads((out / "transforms.json").read_text())
    print(
        json.dumps(
            {
                "seconds": round(time.perf_counter() - start, 2),
                "frames": len(meta["frames"]),
                "splits": {
                    k: len(v) for k, v in [("train", meta["train_filenames"]), *meta["eval_splits"].items()]
                },
                "prior": meta["voxnerf_synthetic"]["prior"],
            },
            indent=2,
        )
    )
