"""The render request: the body of ``POST /render``, and what the render task receives and parses again.

The pose and intrinsics rules are the engine's (:mod:`voxnerf.cameras.rules`), the output names and media types
those of :mod:`voxnerf.inference.encoding`; both modules are torch-free, so the API process can validate requests.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.core.jobstore import ID_RE
from voxnerf.cameras.rules import (
    CAMERA_MODELS,
    COEFFICIENT_KEYS,
    CameraError,
    Intrinsics,
    resolve_intrinsics,
    resolve_lens,
    validate_pose,
)
from voxnerf.inference.encoding import MEDIA_TYPES, OUTPUT_NAMES

OutputName = Literal[tuple(OUTPUT_NAMES)]  # rgb, depth, opacity
FormatName = Literal[tuple(MEDIA_TYPES)]  # png, exr
CameraModel = Literal[CAMERA_MODELS]  # PINHOLE, OPENCV, OPENCV_FISHEYE
MAX_SIDE = 16384
EXAMPLE_JOB = "3f2b8c1d9e0a4b5c8d7e6f5a4b3c2d1e"  # of the API reference's examples
EXAMPLE_POSE = [[1, 0, 0, 0.5], [0, 1, 0, 0.2], [0, 0, 1, 2.0], [0, 0, 0, 1]]


class RenderRequest(BaseModel):
    """One view of a finished job. Missing intrinsics come from the scene's first training camera.

    ``width``/``height`` come together; when given, every missing intrinsic is the default scaled by
    ``width / default width`` (x) and ``height / default height`` (y). PNG holds one output: ``rgb`` (8-bit
    sRGB-encoded colour), ``depth`` (16-bit, in the scene's ``depth_unit_scale_factor`` units) or ``opacity``
    (8-bit gray). EXR holds any of them as float32 channels R, G, B, Z (depth, scene units) and A (opacity).
    Default outputs: ``["rgb"]`` for PNG, all three for EXR.

    Without ``camera_model`` the view is a pinhole: for a scene trained through a lens, its undistorted view.
    ``camera_model`` ``OPENCV`` (``k1 k2 k3 p1 p2``) or ``OPENCV_FISHEYE`` (``k1 k2 k3 k4``) renders through
    that lens, as nerfstudio defines it; a coefficient left out is the trained camera's when it has that model,
    else 0 (:func:`voxnerf.cameras.rules.resolve_intrinsics`, the rule of ``voxnerf render`` too).
    """

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"job_id": EXAMPLE_JOB, "transform_matrix": EXAMPLE_POSE, "width": 640, "height": 480, "format": "png"},
        {"job_id": EXAMPLE_JOB, "transform_matrix": EXAMPLE_POSE, "format": "exr", "outputs": ["rgb", "depth"]}]})

    job_id: str = Field(pattern=ID_RE.pattern, description="a succeeded job's id")
    transform_matrix: list[list[float]] = Field(
        description="4x4 camera-to-world, OpenGL axes (camera looks along -Z, +Y up), scene units"
    )
    width: int | None = Field(None, ge=1, le=MAX_SIDE)
    height: int | None = Field(None, ge=1, le=MAX_SIDE)
    fl_x: float | None = Field(None, gt=0)
    fl_y: float | None = Field(None, gt=0)
    cx: float | None = None
    cy: float | None = None
    camera_model: CameraModel | None = Field(None, description="lens to render through; absent: pinhole")
    k1: float | None = None
    k2: float | None = None
    k3: float | None = None
    k4: float | None = None
    p1: float | None = None
    p2: float | None = None
    format: FormatName = "png"
    outputs: list[OutputName] | None = None
    antialias: bool | None = Field(
        None, description="false: each pixel's colour from its centre ray alone, a fifth of the rays (the viewer's "
        "frames while the camera moves); absent: the job's antialias setting (five rays per pixel by default)")

    @field_validator("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2")
    @classmethod
    def _finite(cls, value: float | None) -> float | None:
        if value is not None and not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @field_validator("transform_matrix")
    @classmethod
    def _pose(cls, value: list[list[float]]) -> list[list[float]]:
        """The engine's pose rule (:func:`voxnerf.cameras.rules.validate_pose`); small deviations of the
        rotation are re-orthonormalised."""
        try:
            return validate_pose(value).tolist()
        except CameraError as err:
            raise ValueError(str(err)) from None

    @model_validator(mode="after")
    def _consistent(self) -> RenderRequest:
        if (self.width is None) != (self.height is None):
            raise ValueError("give width and height together (or neither, for the scene's size)")
        if self.outputs is None:
            self.outputs = ["rgb"] if self.format == "png" else list(OUTPUT_NAMES)
        self.outputs = list(dict.fromkeys(self.outputs))
        if not self.outputs:
            raise ValueError(f"outputs must name at least one of {', '.join(OUTPUT_NAMES)}")
        if self.format == "png" and len(self.outputs) != 1:
            raise ValueError(
                f"a PNG holds one output: ask for one of {', '.join(OUTPUT_NAMES)}, or use format exr"
            )
        return self

    @model_validator(mode="after")
    def _lens(self) -> RenderRequest:
        """The lens rule without the trained camera (coefficients need camera_model, a model takes only its own
        coefficients); the worker applies it again with the trained camera's lens."""
        try:
            resolve_lens(None, self.camera_model, **self.coefficients())
        except CameraError as err:
            raise ValueError(str(err)) from None
        return self

    def coefficients(self) -> dict[str, float | None]:
        """``k1 k2 k3 k4 p1 p2`` as given (None: left out)."""
        return {key: getattr(self, key) for key in COEFFICIENT_KEYS}

    @property
    def media_type(self) -> str:
        return MEDIA_TYPES[self.format]

    def pixels(self) -> int | None:
        """width x height when given (the default size is the scene's own)."""
        return None if self.width is None else self.width * int(self.height)

    def intrinsics(self, default: Intrinsics, max_pixels: int | None = None) -> Intrinsics:
        """The camera to render, filling what the request leaves out from ``default`` (see the class doc);
        raises :class:`voxnerf.cameras.rules.CameraError` when the result is not a usable camera or has more
        than ``max_pixels`` pixels."""
        return resolve_intrinsics(
            default,
            width=self.width,
            height=self.height,
            fl_x=self.fl_x,
            fl_y=self.fl_y,
            cx=self.cx,
            cy=self.cy,
            max_pixels=max_pixels,
            camera_model=self.camera_model,
            **self.coefficients(),
        )
