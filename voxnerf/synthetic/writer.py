"""Writing the room as a docs/scene-format.md scene: transforms.json, sRGB and depth PNGs, the prior and true mesh."""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh

from voxnerf.cameras.rules import COEFFICIENT_KEYS, MODEL_COEFFICIENTS, CameraError, Lens, lens_of
from voxnerf.data.image_io import build_dir_atomic
from voxnerf.synthetic.cameras import FrameSplits, camera_path, split_frames
from voxnerf.synthetic.dimensions import ROOM_SIZE
from voxnerf.synthetic.geometry import RoomGeometry
from voxnerf.synthetic.priors import PRIOR_KINDS, noisy_mesh_prior, sample_point_prior
from voxnerf.synthetic.raycast import AMBIENT, Shading, linear_to_srgb, render_radiance
from voxnerf.synthetic.room import LIGHT_TEMPERATURE_RANGE_K, ROOM_SIZE_RANGE, RoomStyle, build_room
from voxnerf.synthetic.sensor import CameraResponse, capture_linear, drift_walk, sensor_depth, vignette_gain

HORIZONTAL_FOV_DEG = 65.0
# What this writer's scenes hold changed (1: no top-level "synthetic"; 2: it is true); stored as
# voxnerf_synthetic.writer, so a cached room written by an older writer is rendered again (written_by_this_writer).
WRITER_VERSION = 2
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
    # Variety (room.RoomStyle and raycast.Shading say what each does); defaults: the room as it always was.
    room_size: tuple[float, float, float] | None = None
    """(W, D, H) metres within ``room.ROOM_SIZE_RANGE``; None: ``ROOM_SIZE``."""
    ambient: float = AMBIENT
    light_scale: float = 1.0
    light_temperature_k: float | None = None
    light_jitter_m: float = 0.0
    texture_scale: float = 1.0
    palette_shift: float = 0.0
    # Capture-like rendering (raycast.Shading, sensor.CameraResponse); defaults: off.
    light_radius_m: float = 0.0
    shadow_rays: int = 1
    gi_bounces: int = 0
    gi_rays: int = 4
    noise_photons: float = 0.0
    noise_read_std: float = 0.0
    exposure_drift_ev: float = 0.0
    """Peak |EV| of the smooth random walk of exposure along the path (0: fixed exposure)."""
    white_balance_drift_ev: float = 0.0
    """Peak |EV| of the red and blue gains' own walks against green (0: fixed white balance)."""
    vignetting: float = 0.0
    sensor_depth: bool = False
    """Depth PNGs like a Kinect's (``sensor.sensor_depth``) instead of the true z-depth."""

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
        self._validate_style()

    def _validate_style(self) -> None:
        """ValueError naming the first bad style or capture field."""
        self._validate_room_size()
        for name, (lo, hi) in _RANGES.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:
                raise ValueError(f"RoomSpec.{name} must be a number in [{lo}, {hi}], got {value!r}")
        kelvin = self.light_temperature_k
        if kelvin is not None and not (
            isinstance(kelvin, int | float) and LIGHT_TEMPERATURE_RANGE_K[0] <= kelvin <= LIGHT_TEMPERATURE_RANGE_K[1]
        ):
            raise ValueError(
                f"RoomSpec.light_temperature_k must be None or kelvin in {list(LIGHT_TEMPERATURE_RANGE_K)}, "
                f"got {kelvin!r}"
            )
        for name, lo, hi in (("shadow_rays", 1, 64), ("gi_rays", 1, 64), ("gi_bounces", 0, 2)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ValueError(f"RoomSpec.{name} must be an integer in [{lo}, {hi}], got {value!r}")
        if not isinstance(self.sensor_depth, bool):
            raise ValueError(f"RoomSpec.sensor_depth must be true or false, got {self.sensor_depth!r}")

    def _validate_room_size(self) -> None:
        if self.room_size is None:
            return
        size = self.room_size
        if not (isinstance(size, list | tuple) and len(size) == 3 and all(
            isinstance(v, int | float) and not isinstance(v, bool) and lo <= v <= hi
            for v, (lo, hi) in zip(size, ROOM_SIZE_RANGE, strict=True)
        )):
            raise ValueError(
                f"RoomSpec.room_size must be None or (W, D, H) metres within {[list(r) for r in ROOM_SIZE_RANGE]}, "
                f"got {size!r}"
            )

    def room_style(self) -> RoomStyle:
        """The room's :class:`RoomStyle` (size, lights, textures)."""
        return RoomStyle(
            tuple(float(v) for v in self.room_size) if self.room_size is not None else ROOM_SIZE,
            self.light_scale, self.light_temperature_k, self.light_jitter_m, self.texture_scale, self.palette_shift,
        )

    def shading(self) -> Shading:
        """How the room is lit (:class:`Shading`)."""
        return Shading(self.ambient, self.light_radius_m, self.shadow_rays, self.gi_bounces, self.gi_rays)

    def camera_response(self) -> CameraResponse:
        """What the camera does to the radiance (:class:`CameraResponse`)."""
        return CameraResponse(self.noise_photons, self.noise_read_std, self.vignetting)


_RANGES: dict[str, tuple[float, float]] = {
    "ambient": (0.0, 2.0),
    "light_scale": (0.05, 20.0),
    "light_jitter_m": (0.0, 0.5),
    "texture_scale": (0.25, 4.0),
    "palette_shift": (0.0, 1.0),
    "light_radius_m": (0.0, 0.15),
    "noise_photons": (0.0, 1e6),
    "noise_read_std": (0.0, 0.1),
    "exposure_drift_ev": (0.0, 2.0),
    "white_balance_drift_ev": (0.0, 1.0),
    "vignetting": (0.0, 1.0),
}
"""Inclusive ranges of RoomSpec's numeric style and capture fields (every bound is finite, so NaN fails)."""
_OPTIONAL_FIELDS = ("lens", *(f.name for f in fields(RoomSpec) if f.name not in {
    "width", "height", "n_frames", "train_every", "n_gaps", "gap_len", "prior_kind", "prior_sigma",
    "prior_max_points", "write_depth", "supersample", "seed", "hfov_deg", "lens"}))
"""Fields written to transforms.json only when they differ from their defaults (older scenes stay as they were)."""


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, image, extension=".png")


def _check_out_dir(out_dir: Path) -> None:
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir}: output must not exist or be an empty directory")


def written_by_this_writer(room: Path) -> bool:
    """Whether ``room/transforms.json`` exists and records :data:`WRITER_VERSION` (a room cached by an older
    writer lacks what scenes hold now, and callers that cache rooms render it again)."""
    try:
        meta = json.loads((room / "transforms.json").read_text())
    except (OSError, ValueError):
        return False
    record = meta.get("voxnerf_synthetic") if isinstance(meta, dict) else None
    return isinstance(record, dict) and record.get("writer") == WRITER_VERSION


def make_room_scene(out_dir: Path, spec: RoomSpec | None = None) -> Path:
    """Render the synthetic room into ``out_dir`` (which must not exist or be empty); returns ``out_dir``.

    Writes ``transforms.json``, ``images/frame-NNNNNN.png`` (sRGB), ``depth/frame-NNNNNN.png`` (16-bit mm) for
    the frames some split uses, ``prior.ply`` (unless ``prior_kind == "none"``) and ``gt_mesh.ply``. The whole
    directory is built beside ``out_dir`` and renamed into place, so a partial scene is never visible.
    Same spec -> byte-identical files. With exposure or white-balance drift, ``voxnerf_synthetic.capture_ev``
    records each written frame's exposure and red / blue gains (EV, in ``frames`` order).
    """
    spec = spec or RoomSpec()
    spec.validate()
    out_dir = Path(out_dir)
    _check_out_dir(out_dir)
    splits = split_frames(spec.n_frames, spec.train_every, spec.n_gaps, spec.gap_len)
    build_dir_atomic(out_dir, lambda tmp: _write_scene(tmp, spec, splits), _check_out_dir)
    return out_dir



def _write_scene(root: Path, spec: RoomSpec, splits: FrameSplits) -> None:
    geom = build_room(spec.seed, spec.room_style())
    w, h = spec.width, spec.height
    fl = (w / 2) / math.tan(math.radians(spec.hfov_deg) / 2)
    meta: dict = {"camera_model": "PINHOLE", "fl_x": fl, "fl_y": fl, "cx": w / 2, "cy": h / 2, "w": w, "h": h}
    lens = spec.camera_lens()
    if lens is not None:  # nerfstudio's keys: the model and every coefficient it has
        meta["camera_model"] = lens.model
        meta.update({key: getattr(lens, key) for key in MODEL_COEFFICIENTS[lens.model]})
    if spec.write_depth:
        meta["depth_unit_scale_factor"] = DEPTH_UNIT_SCALE
    meta["synthetic"] = True  # rendered with exact poses (voxnerf/training/stages/corrections.py)
    drift = _drift(spec)
    meta["frames"] = _write_frames(root, spec, geom, splits.used, fl, drift)
    meta.update(_split_lists(splits))
    prior_info = _write_prior(root, spec, geom)
    if prior_info is not None:
        meta["prior_file_path"] = "prior.ply"
        meta["prior_sigma"] = spec.prior_sigma
    geom.to_trimesh().export(root / "gt_mesh.ply")
    meta["voxnerf_synthetic"] = _generator_record(spec, splits, geom, prior_info)
    if drift.any():
        meta["voxnerf_synthetic"]["capture_ev"] = {
            "exposure": [round(float(drift[i, 1]), 6) for i in splits.used],
            "red": [round(float(drift[i, 0] - drift[i, 1]), 6) for i in splits.used],
            "blue": [round(float(drift[i, 2] - drift[i, 1]), 6) for i in splits.used],
        }
    (root / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")


def _drift(spec: RoomSpec) -> np.ndarray:
    """Per path frame log2 gains [n_frames, 3] (R, G, B): the exposure walk, plus the red and blue walks."""
    exposure = drift_walk(spec.n_frames, spec.exposure_drift_ev, np.random.default_rng([spec.seed, 4]))
    wb_rng = np.random.default_rng([spec.seed, 5])
    red, blue = (drift_walk(spec.n_frames, spec.white_balance_drift_ev, wb_rng) for _ in range(2))
    return np.stack([exposure + red, exposure, exposure + blue], axis=1)


def _write_frames(
    root: Path, spec: RoomSpec, geom: RoomGeometry, indices: list[int], fl: float, drift: np.ndarray
) -> list[dict]:
    """Render and write the frames ``indices`` of the camera path; their transforms.json ``frames`` entries.

    A frame's random values (soft shadows, indirect light, noise, depth) come from ``[seed, 3, index]``.
    """
    poses = camera_path(spec.n_frames, geom.room_size)
    w, h = spec.width, spec.height
    shading, response = spec.shading(), spec.camera_response()
    vignette = vignette_gain(w, h, fl, w / 2, h / 2, spec.vignetting) if spec.vignetting > 0 else None
    captured = not response.is_identity or drift.any()
    frames = []
    for i in indices:
        name = f"frame-{i:06d}.png"
        rng = np.random.default_rng([spec.seed, 3, i])
        view = render_radiance(geom, poses[i], fl, w / 2, h / 2, w, h, spec.supersample, spec.camera_lens(),
                               shading, rng)
        linear = capture_linear(view.radiance, 2.0 ** drift[i], vignette, response, rng) if captured else view.radiance
        rgb = linear_to_srgb(linear).astype(np.float32)
        _write_png(root / "images" / name, np.round(rgb * 255).astype(np.uint8))
        frame = {"file_path": f"images/{name}", "transform_matrix": np.round(poses[i], 8).tolist()}
        if spec.write_depth:
            depth = sensor_depth(view.depth, view.cos_incidence, rng) if spec.sensor_depth else view.depth
            depth_units = np.clip(np.round(depth.astype(np.float32) / DEPTH_UNIT_SCALE), 0, 65535).astype(np.uint16)
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
    """``asdict(spec)`` without the optional fields left at their defaults (so older scenes' files stay as they
    were: a pinhole default room is written as before these fields existed)."""
    defaults = asdict(RoomSpec())
    record = asdict(spec)
    for name in _OPTIONAL_FIELDS:
        if record[name] == defaults[name]:
            del record[name]
    return record


def _generator_record(spec: RoomSpec, splits: FrameSplits, geom: RoomGeometry, prior_info: dict | None) -> dict:
    """transforms.json ``voxnerf_synthetic``: how the scene was made and where its objects are."""
    return {
        "writer": WRITER_VERSION,
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
