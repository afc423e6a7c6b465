"""Synthetic indoor test scene: a textured, furnished room ray-cast on the CPU, written as docs/scene-format.md.

World frame: metres, +Z up, the room spans ``x in [-W/2, W/2]``, ``y in [-D/2, D/2]``, ``z in [0, H]``.
Cameras are camera-to-world in the OpenGL / nerfstudio convention (camera looks along -Z, +Y up, +X right).

The room is built from trimesh primitives (boxes, cylinders) placed deterministically from a seed, each
object with a procedural solid texture evaluated at the 3D hit point (no UVs). Images are Lambertian:
ambient light plus two point lights with shadow rays, supersampled, written as 8-bit sRGB PNGs. ``RoomSpec``'s
style fields (default: off) vary the room's size, lights and textures and make it look like a capture: area
lights (soft shadows), diffuse indirect light, sensor noise, exposure and white-balance drift, vignetting and
Kinect-like depth. Splits mimic
the real redkitchen scene (``shared/data/README.md``): every ``train_every``-th frame trains except inside
``n_gaps`` gaps; interpolation frames lie midway between training frames, extrapolation frames in the gaps.

Submodules, in dependency order:

- ``dimensions``: ``ROOM_SIZE``;
- ``textures``: :class:`Material` and the procedural patterns;
- ``geometry``: the room as a triangle soup (:class:`RoomGeometry`) and its builder;
- ``furniture``: the furniture and lights as data; ``room``: :func:`build_room` reads them for a seed;
- ``raycast``: :class:`Shading`, :func:`shade` and :func:`render_view` / :func:`render_radiance`;
- ``sensor``: the camera's response (drift, vignetting, noise) and Kinect-like depth;
- ``cameras``: :func:`camera_path` and :func:`split_frames`;
- ``priors``: noisy point-cloud and mesh priors;
- ``writer``: :class:`RoomSpec` and :func:`make_room_scene` (also ``python -m voxnerf.synthetic OUT_DIR [SEED]``);
- ``suite``: the tuning suite's named rooms and ``make_suite`` (``python -m voxnerf.synthetic.suite OUT_DIR``).
"""

from voxnerf.synthetic.cameras import FrameSplits, camera_path, look_at_c2w, split_frames
from voxnerf.synthetic.dimensions import ROOM_SIZE
from voxnerf.synthetic.geometry import PointLight, RoomGeometry, RoomObject
from voxnerf.synthetic.priors import (
    PRIOR_HOLE_RADIUS,
    PRIOR_HOLES,
    PRIOR_KINDS,
    PRIOR_MESH_MAX_EDGE,
    PRIOR_OUTLIER_FRACTION,
    noisy_mesh_prior,
    sample_point_prior,
)
from voxnerf.synthetic.raycast import (
    AMBIENT,
    LIGHT_FALLOFF_M,
    SHADOW_OFFSET_M,
    Shading,
    ViewRender,
    render_radiance,
    render_view,
    shade,
)
from voxnerf.synthetic.room import ROOM_SIZE_RANGE, RoomStyle, build_room
from voxnerf.synthetic.sensor import CameraResponse
from voxnerf.synthetic.textures import Material
from voxnerf.synthetic.writer import DEPTH_UNIT_SCALE, HORIZONTAL_FOV_DEG, RoomSpec, make_room_scene

__all__ = [
    "AMBIENT",
    "CameraResponse",
    "DEPTH_UNIT_SCALE",
    "HORIZONTAL_FOV_DEG",
    "LIGHT_FALLOFF_M",
    "PRIOR_HOLES",
    "PRIOR_HOLE_RADIUS",
    "PRIOR_KINDS",
    "PRIOR_MESH_MAX_EDGE",
    "PRIOR_OUTLIER_FRACTION",
    "ROOM_SIZE",
    "ROOM_SIZE_RANGE",
    "SHADOW_OFFSET_M",
    "FrameSplits",
    "Material",
    "PointLight",
    "RoomGeometry",
    "RoomObject",
    "RoomSpec",
    "RoomStyle",
    "Shading",
    "ViewRender",
    "build_room",
    "camera_path",
    "look_at_c2w",
    "make_room_scene",
    "noisy_mesh_prior",
    "render_radiance",
    "render_view",
    "sample_point_prior",
    "shade",
    "split_frames",
]
