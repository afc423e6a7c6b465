"""The render request: the body of ``POST /render``, and what the render task receives and parses again.

The pose and intrinsics rules are the engine's (:mod:`voxnerf.camera_rules`), the output names and media types
those of :mod:`voxnerf.outputs`; both modules are torch-free, so the API process can validate requests.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.core.jobstore import ID_RE
from voxnerf.camera_rules import CameraError, Intrinsics, resolve_intrinsics, validate_pose
from voxnerf.outputs import MEDIA_TYPES, OUTPUT_NAMES

OutputName = Literal[tuple(OUTPUT_NAMES)]  # rgb, depth, opacity
FormatName = Literal[tuple(MEDIA_TYPES)]  # png, exr
MAX_SIDE = 16384


class RenderRequest(BaseModel):
    """One view of a finished job. Missing intrinsics come from the scene's first training camera.

    ``width``/``height`` come together; when given, every missing intrinsic is the default scaled by
    ``width / default width`` (x) and ``height / default height`` (y). PNG holds one output: ``rgb`` (8-bit
    sRGB-encoded colour), ``depth`` (16-bit, in the scene's ``depth_unit_scale_factor`` units) or ``opacity``
    (8-bit gray). EXR holds any of them as float32 channels R, G, B, Z (depth, scene units) and A (opacity).
    Default outputs: ``["rgb"]`` for PNG, all three for EXR.
    """

    model_config = ConfigDict(extra="forbid")

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
    format: FormatName = "png"
    outputs: list[OutputName] | None = None

    @field_validator("fl_x", "fl_y", "cx", "cy")
    @classmethod
    def _finite(cls, value: float | None) -> float | None:
        if value is not None and not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @field_validator("transform_matrix")
    @classmethod
    def _pose(cls, value: list[list[float]]) -> list[list[float]]:
        """The engine's pose rule (:func:`voxnerf.camera_rules.validate_pose`); small deviations of the
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

    @property
    def media_type(self) -> str:
        return MEDIA_TYPES[self.format]

    def pixels(self) -> int | None:
        """width x height when given (the default size is the scene's own)."""
        return None if self.width is None else self.width * int(self.height)

    def intrinsics(self, default: Intrinsics, max_pixels: int | None = None) -> Intrinsics:
        """The camera to render, filling what the request leaves out from ``default`` (see the class doc);
        raises :class:`voxnerf.camera_rules.CameraError` when the result is not a usable camera or has more
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
        )
