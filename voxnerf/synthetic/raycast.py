"""Ray casting the room: closest hits with open3d, Lambertian shading with shadow rays, pinhole views (optionally
through an OpenCV lens, :mod:`voxnerf.cameras.lens`: each pixel's ray goes through the inverse distortion).

Cameras are camera-to-world in the OpenGL / nerfstudio convention (camera looks along -Z, +Y up, +X right).
Images are Lambertian: ambient light plus the room's point lights with shadow rays (by default; a
:class:`Shading` adds area lights and diffuse indirect light), supersampled, returned as sRGB-encoded colour in
[0, 1] (or linear radiance) together with the z-depth at each pixel centre.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from voxnerf.cameras.lens import LensBatch, lens_directions
from voxnerf.cameras.rules import Lens
from voxnerf.synthetic.geometry import RoomGeometry
from voxnerf.synthetic.textures import PATTERNS

AMBIENT = 0.22
LIGHT_FALLOFF_M = 2.5
"""Metres at which a point light's irradiance halves (``1 / (1 + (d / LIGHT_FALLOFF_M)^2)``)."""
SHADOW_OFFSET_M = 1e-3
MIN_LENS_COS = 0.05
"""A lens whose rays reach ``acos(MIN_LENS_COS)`` (87 degrees) off the optical axis is refused (z-depth rays)."""


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB encoding of linear values (any shape), clipped to [0, 1] first."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _o3d_rays(origins: np.ndarray, dirs: np.ndarray):
    """open3d's [N, 6] float32 ray tensor of ``origins`` and ``dirs`` [N, 3]."""
    import open3d as o3d  # imported where used: a machine without open3d can still load the package

    return o3d.core.Tensor(np.concatenate([origins, dirs], axis=1).astype(np.float32))


def _cast(
    geom: RoomGeometry, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest hits: ``t`` [N] in units of |dir| (inf on a miss), triangle ids int64 [N] (-1 on a miss),
    triangle normals [N, 3]."""
    rays = _o3d_rays(origins, dirs)
    hit = geom.raycasting_scene.cast_rays(rays)
    t = hit["t_hit"].numpy().astype(np.float64)
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    prim[~np.isfinite(t)] = -1
    return t, prim, hit["primitive_normals"].numpy().astype(np.float64)


def _albedo(geom: RoomGeometry, points: np.ndarray, normals: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """Linear albedo [N, 3] in [0, 1] at hit ``points`` [N, 3] with ``normals`` [N, 3] on ``objects`` [N]."""
    albedo = np.zeros((len(points), 3))
    order = np.argsort(objects, kind="stable")
    ids, starts = np.unique(objects[order], return_index=True)
    for obj_id, sel in zip(ids, np.split(order, starts[1:]), strict=True):
        material = geom.objects[obj_id].material
        albedo[sel] = PATTERNS[material.pattern](
            points[sel], normals[sel], material, geom.seed * 1000 + int(obj_id), room_height=geom.room_size[2]
        )
    return np.clip(albedo, 0.0, 1.0)


@dataclass(frozen=True)
class Shading:
    """How surfaces are lit (the defaults: ambient plus point lights with hard shadows, no indirect light).

    ``ambient``: irradiance every surface receives; ``light_radius_m``: each light is a sphere of this radius
    sampled by ``shadow_rays`` random shadow rays per shading point (soft shadows), 0 for a point light (one
    exact ray); ``gi_bounces``: bounces of diffuse indirect light, gathered by ``gi_rays`` cosine-weighted rays
    per shading point at the first bounce and one at later ones.
    """

    ambient: float = AMBIENT
    light_radius_m: float = 0.0
    shadow_rays: int = 1
    gi_bounces: int = 0
    gi_rays: int = 4

    @property
    def is_random(self) -> bool:
        """Whether shading draws random rays (then :func:`shade` needs a generator)."""
        return self.light_radius_m > 0 or self.gi_bounces > 0


def shade(
    geom: RoomGeometry, origins: np.ndarray, dirs: np.ndarray, shading: Shading | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Trace rays (origins, dirs [N, 3], any direction length): linear radiance [N, 3], 0 on a miss.

    Lambertian: ``albedo * (ambient + sum_l visible_l * I_l * max(0, n.l) / (1 + (d_l / LIGHT_FALLOFF_M)^2)
    + indirect) + emission * albedo``, surfaces two-sided (normals flipped toward the ray), shadows by occlusion
    rays (``visible_l`` the fraction of an area light's samples seen). ``rng`` is needed when
    ``shading.is_random``.
    """
    shading = shading or Shading()
    if shading.is_random and rng is None:
        raise ValueError("soft shadows and indirect light need a random generator (rng)")
    t, prim, normals = _cast(geom, origins, dirs)
    radiance = np.zeros((len(t), 3))
    hit = prim >= 0
    if not hit.any():
        return radiance
    points = origins[hit] + t[hit, None] * dirs[hit]
    n = normals[hit]
    n = np.where((np.sum(n * dirs[hit], axis=1) > 0)[:, None], -n, n)
    objects = geom.triangle_object[prim[hit]]
    albedo = _albedo(geom, points, n, objects)
    emission = np.array([m.material.emission for m in geom.objects])[objects]
    irradiance = np.full((len(points), 3), shading.ambient)
    start = points + SHADOW_OFFSET_M * n
    for light in geom.lights:
        to_light = np.asarray(light.position)[None] - start
        dist = np.linalg.norm(to_light, axis=1)
        cosine = np.maximum(np.sum(n * to_light, axis=1) / np.maximum(dist, 1e-9), 0.0)
        lit = cosine > 0
        visible = light_visibility(geom, start, lit, light.position, shading, rng)
        falloff = 1.0 / (1.0 + (dist / LIGHT_FALLOFF_M) ** 2)
        irradiance += (visible * cosine * falloff)[:, None] * np.asarray(light.intensity)[None]
    if shading.gi_bounces > 0:
        irradiance += _indirect(geom, start, n, shading, rng)
    radiance[hit] = albedo * irradiance + emission[:, None] * albedo
    return radiance


def light_visibility(
    geom: RoomGeometry, start: np.ndarray, lit: np.ndarray, position: tuple[float, float, float],
    shading: Shading, rng: np.random.Generator | None,
) -> np.ndarray:
    """Fraction [N] in [0, 1] of the light at ``position`` seen from ``start`` [N, 3] (0 where not ``lit`` [N]).

    A point light (``light_radius_m == 0``): one ray each, so 0 or 1. An area light: ``shadow_rays`` rays each
    to uniform random points on its sphere.
    """
    visible = np.zeros(len(start))
    if shading.light_radius_m == 0:
        to_light = np.asarray(position)[None] - start[lit]
        rays = _o3d_rays(start[lit], to_light)
        occluded = geom.raycasting_scene.test_occlusions(rays, tnear=0.0, tfar=1.0).numpy()
        visible[np.flatnonzero(lit)[~occluded]] = 1.0
        return visible
    k = shading.shadow_rays
    origins = np.repeat(start[lit], k, axis=0)
    on_sphere = rng.normal(size=origins.shape)
    on_sphere *= shading.light_radius_m / np.maximum(np.linalg.norm(on_sphere, axis=1, keepdims=True), 1e-12)
    to_light = np.asarray(position)[None] + on_sphere - origins
    rays = _o3d_rays(origins, to_light)
    occluded = geom.raycasting_scene.test_occlusions(rays, tnear=0.0, tfar=1.0).numpy()
    visible[lit] = (~occluded).reshape(-1, k).mean(axis=1)
    return visible


def _indirect(
    geom: RoomGeometry, start: np.ndarray, n: np.ndarray, shading: Shading, rng: np.random.Generator
) -> np.ndarray:
    """Diffuse indirect irradiance [N, 3] at ``start`` [N, 3] with normals ``n`` [N, 3]: the mean radiance of
    ``shading.gi_rays`` cosine-weighted hemisphere rays (the Lambertian estimator), shaded with one bounce fewer."""
    k = shading.gi_rays
    normals = np.repeat(n, k, axis=0)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    tangent = np.cross(normals, helper)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    bitangent = np.cross(normals, tangent)
    u, phi = rng.random(len(normals)), 2 * np.pi * rng.random(len(normals))
    radius = np.sqrt(u)
    dirs = (radius * np.cos(phi))[:, None] * tangent + (radius * np.sin(phi))[:, None] * bitangent
    dirs += np.sqrt(1.0 - u)[:, None] * normals
    inner = replace(shading, gi_bounces=shading.gi_bounces - 1, gi_rays=1, shadow_rays=1)
    incoming = shade(geom, np.repeat(start, k, axis=0), dirs, inner, rng)
    return incoming.reshape(-1, k, 3).mean(axis=1)


def _undistorted(lens: Lens, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted pinhole coordinates (OpenCV axes) of distorted normalised ``u, v`` [N], in float64."""
    uv = torch.from_numpy(np.stack([u, v], axis=-1).astype(np.float64))
    d = lens_directions(uv, LensBatch.of([lens], dtype=torch.float64)).numpy()
    if d[:, 2].min() < MIN_LENS_COS:
        raise ValueError(f"the lens {lens} sees more than {np.degrees(np.arccos(MIN_LENS_COS)):.0f} degrees off axis")
    return d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]


def _pixel_rays(c2w: np.ndarray, fl: float, cx: float, cy: float, px: np.ndarray, py: np.ndarray,
                lens: Lens | None = None):
    """World rays through continuous pixel coordinates ``(px, py)`` [N]; dirs have camera z-component -1.

    The ray parameter of a hit is therefore its z-depth along the camera's -Z axis (OpenGL convention).
    With a ``lens`` the pixel's normalised coordinates go through its inverse distortion first.
    """
    right, up, back = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2]
    if lens is None:
        # Camera direction ((px - cx) / fl, -(py - cy) / fl, -1) rotated to world, without a (slow here) BLAS call.
        dirs = ((px - cx) / fl)[:, None] * right - ((py - cy) / fl)[:, None] * up - back
    else:
        x, y = _undistorted(lens, (px - cx) / fl, (py - cy) / fl)
        dirs = x[:, None] * right - y[:, None] * up - back
    return np.broadcast_to(c2w[:3, 3], dirs.shape).copy(), dirs


@dataclass
class ViewRender:
    """One rendered view: ``radiance`` float64 [h, w, 3] linear (the supersampled mean), ``depth`` float64
    [h, w] z-depth (m) at pixel centres (0 on a miss), ``cos_incidence`` float64 [h, w] |cos| of the angle
    between each centre ray and the surface it hits (0 on a miss)."""

    radiance: np.ndarray
    depth: np.ndarray
    cos_incidence: np.ndarray


def render_radiance(
    geom: RoomGeometry, c2w: np.ndarray, fl: float, cx: float, cy: float, w: int, h: int, supersample: int = 2,
    lens: Lens | None = None, shading: Shading | None = None, rng: np.random.Generator | None = None,
) -> ViewRender:
    """Render one view of the room in linear radiance (arguments as :func:`render_view`; ``shading`` and
    ``rng`` as :func:`shade`)."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    c2w = np.asarray(c2w, np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample
    py, px, oy, ox = np.meshgrid(np.arange(h), np.arange(w), offsets, offsets, indexing="ij")
    origins, dirs = _pixel_rays(c2w, fl, cx, cy, (px + ox).ravel(), (py + oy).ravel(), lens)
    radiance = shade(geom, origins, dirs, shading, rng).reshape(h, w, supersample * supersample, 3).mean(axis=2)
    cy_grid, cx_grid = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    origins, dirs = _pixel_rays(c2w, fl, cx, cy, cx_grid.ravel(), cy_grid.ravel(), lens)
    t, _, normals = _cast(geom, origins, dirs)
    hit = np.isfinite(t)
    cosine = np.abs(np.sum(normals * dirs, axis=1)) / np.linalg.norm(dirs, axis=1)
    return ViewRender(
        radiance, np.where(hit, t, 0.0).reshape(h, w), np.where(hit, cosine, 0.0).reshape(h, w)
    )


def render_view(
    geom: RoomGeometry, c2w: np.ndarray, fl: float, cx: float, cy: float, w: int, h: int, supersample: int = 2,
    lens: Lens | None = None, shading: Shading | None = None, rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render one view of the room: a pinhole, or a pinhole behind ``lens`` (colour and depth through it).

    Args:
        c2w: [4, 4] camera-to-world, OpenGL convention (camera looks along -Z, +Y up), metres.
        fl: focal length in pixels (fl_x == fl_y); ``cx, cy`` principal point in continuous pixel coordinates.
        supersample: ``s``: colour is the mean of ``s x s`` rays spread evenly over each pixel.
        shading, rng: how surfaces are lit (:class:`Shading`, default: hard shadows, no indirect light) and the
            generator its random rays need.
    Returns:
        rgb: float32 [h, w, 3] sRGB-encoded colour in [0, 1] (the PNG is ``round(255 * rgb)``);
        depth: float32 [h, w] z-depth in metres along the camera's -Z axis at each pixel centre
        ``(x + 0.5, y + 0.5)``, 0 where the ray hits nothing (only possible from outside the room).
    """
    view = render_radiance(geom, c2w, fl, cx, cy, w, h, supersample, lens, shading, rng)
    return linear_to_srgb(view.radiance).astype(np.float32), view.depth.astype(np.float32)
