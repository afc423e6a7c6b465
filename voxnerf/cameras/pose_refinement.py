"""Camera pose refinement: a rigid correction per training image, learnt with the field (nerfacto's SO3 x R3).

Scanned poses (SLAM, KinectFusion, COLMAP) are off by a fraction of a degree and a few millimetres; a ray that
leaves its camera slightly wrong paints colour onto the wrong surface point. Each training image ``i`` gets six
parameters, zero at the start: an axis-angle rotation ``w_i`` and a translation ``t_i`` (normalised units). Its
rays become ``o' = o + t_i`` and ``d' = exp(w_i) d``: the camera turns about its own centre, in world axes, and
moves by ``t_i``. The corrections are held at zero mean over the images (the parameters less their mean), so
the cameras can move against each other but the rig as a whole cannot drift away from the poses evaluation
views are given (a shared turn or shift of every camera fits the training images as well, and an early, still
blurry field pulls that way).

A scan's pose errors drift slowly along its path, so a pose the scan gives for any other view (a held-out frame,
a novel view in the scan's frame) carries about the error of the training cameras near it. Rendering a pose
therefore moves it by the corrections of its nearest training cameras (:meth:`PoseRefinement.correct_views`,
weighted by inverse distance, :mod:`voxnerf.cameras.neighbours`): the correction the model learnt for that part of the
path, from the training images alone.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from voxnerf.cameras.neighbours import blend, checked_cameras, nearest_cameras
from voxnerf.data.scene import SceneTransform

# Below this squared angle (rad^2) the exponential map uses its Taylor series: sin(a)/a and (1-cos(a))/a^2 lose
# every digit to cancellation near zero, and their gradients there would be 0/0.
_SMALL_ANGLE_SQ = 1e-8


def so3_exp(w: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] of axis-angle vectors ``w`` [N, 3] (radians; Rodrigues' formula), finite with
    a finite gradient at and near zero."""
    theta_sq = (w * w).sum(-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta_sq), theta_sq))
    a = torch.where(small, 1.0 - theta_sq / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta_sq / 24.0, (1.0 - torch.cos(theta)) / (theta * theta))
    zero = torch.zeros_like(w[:, 0])
    k = torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], -1).view(-1, 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a[:, None, None] * k + b[:, None, None] * (k @ k)


class PoseRefinement(nn.Module):
    """Per training image a rotation and a translation; identity at initialisation.

    ``delta``: [images, 6] parameters, axis-angle (radians) then translation (normalised units); the corrections
    applied are ``delta`` less its mean over the images (:meth:`corrections`).
    ``forward(origins [R, 3], dirs [R, 3] unit, image [R] int64) -> (origins', dirs')``, dirs' still unit
    (:func:`moved_rays` with :meth:`corrections`).
    """

    def __init__(self, images: int, cameras: Tensor | None = None) -> None:
        super().__init__()
        if images < 1:
            raise ValueError(f"PoseRefinement needs at least one image, got {images}")
        self.delta = nn.Parameter(torch.zeros(images, 6))
        # [images, 4, 4] the training cameras' given poses (normalised units), where correct_views looks
        self.register_buffer("cameras", checked_cameras(images, cameras, "PoseRefinement"))

    def corrections(self) -> Tensor:
        """[images, 6] the corrections as applied: ``delta`` less its mean over the images."""
        return self.delta - self.delta.mean(0)

    def forward(self, origins: Tensor, dirs: Tensor, image: Tensor) -> tuple[Tensor, Tensor]:
        return moved_rays(self.corrections(), origins, dirs, image)

    def refined_c2w(self, c2w: Tensor) -> Tensor:
        """[images, 4, 4] camera-to-world poses (normalised units, on any device) with the learnt corrections
        applied, on ``c2w``'s device."""
        return _moved(c2w, self.corrections().detach().to(c2w.device, c2w.dtype))

    def view_corrections(self, c2w: Tensor) -> Tensor:
        """[M, 6] corrections for poses ``c2w`` [M, 4, 4] (normalised units): those of the nearest training
        cameras, blended by inverse distance (:func:`voxnerf.cameras.neighbours.nearest_cameras`). A training camera's
        own pose gets its own correction."""
        return blend(self.corrections().detach(), *nearest_cameras(self.cameras, c2w))

    def correct_views(self, c2w: Tensor) -> Tensor:
        """[M, 4, 4] poses ``c2w`` (normalised units) moved by :meth:`view_corrections`."""
        return _moved(c2w, self.view_corrections(c2w))

    def summary(self, scene_scale: float) -> dict:
        """Size of the learnt corrections (for the report): rotations in degrees, translations in scene units
        (``scene_scale``: normalised units per scene unit), each as mean and max over the images."""
        delta = self.corrections().detach().cpu()
        angles = torch.rad2deg(delta[:, :3].norm(dim=-1))
        moves = delta[:, 3:].norm(dim=-1) / scene_scale
        return {"images": int(delta.shape[0]),
                "rotation_deg": {"mean": float(angles.mean()), "max": float(angles.max())},
                "translation": {"mean": float(moves.mean()), "max": float(moves.max())}}


def moved_rays(corrections: Tensor, origins: Tensor, dirs: Tensor, image: Tensor) -> tuple[Tensor, Tensor]:
    """Rays ``origins``, ``dirs`` [R, 3] (normalised units, dirs unit) moved by their image's row of
    ``corrections`` [images, 6] (``image`` [R] int64): origins shifted, dirs turned (still unit)."""
    rotation = so3_exp(corrections[:, :3])[image]  # every image's (a few dozen), then gathered per ray
    return origins + corrections[image, 3:], torch.einsum("rij,rj->ri", rotation, dirs)


def pose_penalty(corrections: Tensor, rotation_weight: float, translation_weight: float) -> Tensor:
    """nerfacto's regulariser: the weighted mean norms of the corrections' rotations (radians) and translations
    (``corrections`` [images, 6])."""
    return (rotation_weight * corrections[:, :3].norm(dim=-1).mean()
            + translation_weight * corrections[:, 3:].norm(dim=-1).mean())


def _moved(c2w: Tensor, delta: Tensor) -> Tensor:
    """[M, 4, 4] poses ``c2w`` turned about their centres by ``delta[:, :3]`` and moved by ``delta[:, 3:]``."""
    out = c2w.clone()
    out[:, :3, :3] = so3_exp(delta[:, :3]) @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] + delta[:, 3:]
    return out


def refined_frames(refinement: PoseRefinement, file_paths: list[str], c2w: np.ndarray,
                   transform: SceneTransform) -> dict:
    """The training frames' refined poses in transforms.json's form, ``{"frames": [{"file_path",
    "transform_matrix"}]}``, in scene units: ``c2w`` [images, 4, 4] are the given poses in scene units and
    ``transform`` the scene's normalisation."""
    normalised = torch.from_numpy(transform.c2w_to_normalized(c2w))
    refined = transform.c2w_to_scene(refinement.refined_c2w(normalised).numpy())
    return {"frames": [{"file_path": path, "transform_matrix": m.tolist()}
                       for path, m in zip(file_paths, refined, strict=True)]}
