"""What a geometry export renders, without torch: how many views and at what size (the rules of
:mod:`voxnerf.inference.export`, which renders them), so the service can bound an export's cost before it is
queued (:func:`app.core.outputs.check_output_cost`).

Views: every training camera, and each shifted along :data:`OFFSET_DIRECTIONS`; ``max_views`` keeps that many,
evenly spaced. Every view is a pinhole at the trained resolution scaled down so that its longer side is at most
:data:`MAX_RENDER_SIDE` pixels (:func:`render_camera`).
"""

from __future__ import annotations

from voxnerf.cameras.rules import Intrinsics

MAX_RENDER_SIDE = 320  # pixels: the longer side of every rendered view
OFFSET_DIRECTIONS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))  # along the camera's (right, up)


def render_camera(intrinsics: Intrinsics) -> Intrinsics:
    """``intrinsics`` as a pinhole, scaled down so its longer side is at most :data:`MAX_RENDER_SIDE`."""
    pinhole = intrinsics.undistorted()
    longest = max(pinhole.width, pinhole.height)
    return pinhole if longest <= MAX_RENDER_SIDE else pinhole.scaled(MAX_RENDER_SIDE / longest)


def view_count(train_cameras: int, max_views: int | None = None) -> int:
    """Views an export renders from ``train_cameras`` training cameras: each, and each shifted along every
    offset direction; at most ``max_views`` of them (evenly spaced indices, all distinct)."""
    views = train_cameras * (1 + len(OFFSET_DIRECTIONS))
    return views if max_views is None else min(views, max_views)


def view_size(width: int, height: int) -> tuple[int, int]:
    """The size a training camera of ``width`` x ``height`` pixels is rendered at in an export."""
    view = render_camera(Intrinsics(1.0, 1.0, width / 2, height / 2, width, height))
    return view.width, view.height
