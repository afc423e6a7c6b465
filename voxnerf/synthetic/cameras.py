"""The camera path through the room and its redkitchen-style train / interpolation / extrapolation splits.

Poses are camera-to-world [4, 4] in the OpenGL / nerfstudio convention (camera looks along -Z, +Y up, +X
right). Splits mimic the real redkitchen scene (``shared/data/README.md``): every ``train_every``-th frame
trains except inside ``n_gaps`` gaps; interpolation frames lie midway between training frames, extrapolation
frames in the gaps.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from voxnerf.cameras.paths import look_at
from voxnerf.synthetic.dimensions import ROOM_SIZE


def look_at_c2w(position: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenGL: -Z along ``forward``, +Y toward world +Z, +X right), no roll: the rule of
    :func:`voxnerf.cameras.paths.look_at` with world +Z up."""
    position = np.asarray(position, dtype=np.float64)
    return look_at(position, position + np.asarray(forward, dtype=np.float64), np.array([0.0, 0.0, 1.0]))


def camera_path(n_frames: int, room_size: tuple[float, float, float] = ROOM_SIZE) -> np.ndarray:
    """Camera-to-world poses [n_frames, 4, 4] along one smooth loop through the middle of the room.

    The camera walks an ellipse (semi-axes 1.1 m x 0.55 m in the default room, scaled in x and y with the
    room's width and depth for another ``room_size``) at 1.27-1.63 m height, looking 20-60 degrees off the
    outward radial direction toward walls and furniture, slightly downward, with slowly varying yaw and pitch;
    consecutive frames overlap.
    """
    theta = 2 * np.pi * np.arange(n_frames) / n_frames
    scale_x, scale_y = room_size[0] / ROOM_SIZE[0], room_size[1] / ROOM_SIZE[1]
    poses = np.empty((n_frames, 4, 4))
    for i, th in enumerate(theta):
        position = np.array(
            [(0.1 + 1.1 * np.cos(th)) * scale_x, (-0.15 + 0.55 * np.sin(th)) * scale_y,
             1.45 + 0.18 * np.sin(2 * th + 0.3)]
        )
        yaw = th + 0.7 + 0.35 * np.sin(3 * th + 1.0)
        pitch = -0.22 + 0.12 * np.sin(2 * th + 2.0)
        forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
        poses[i] = look_at_c2w(position, forward)
    return poses


@dataclass(frozen=True)
class FrameSplits:
    """Frame indices (into the camera path) of each split, ascending."""

    train: list[int]
    interpolation: list[int]
    extrapolation: list[int]

    @property
    def used(self) -> list[int]:
        """Every frame some split names, ascending."""
        return sorted(set(self.train) | set(self.interpolation) | set(self.extrapolation))


def split_frames(n_frames: int, train_every: int, n_gaps: int, gap_len: int) -> FrameSplits:
    """Redkitchen-style splits along a path of ``n_frames``.

    Training: every ``train_every``-th frame except those within ``gap_len / 2`` of the centres of
    ``n_gaps`` evenly spaced gaps. Interpolation: the frame midway (``+ train_every // 2``) between two
    consecutive training frames. Extrapolation: frames on the ``train_every // 2`` grid inside a gap that are
    at least ``train_every`` frames from every training frame.
    """
    if train_every < 2:
        raise ValueError(f"train_every must be >= 2, got {train_every}")
    if n_gaps < 0 or gap_len < 0:
        raise ValueError(f"n_gaps and gap_len must be >= 0, got {n_gaps}, {gap_len}")
    centres = [(k + 0.5) * n_frames / n_gaps for k in range(n_gaps)]
    train = [i for i in range(0, n_frames, train_every) if all(abs(i - c) >= gap_len / 2 for c in centres)]
    if len(train) < 2:
        raise ValueError(
            f"only {len(train)} training frame(s) left: n_frames={n_frames}, train_every={train_every}, "
            f"n_gaps={n_gaps}, gap_len={gap_len}"
        )
    half = train_every // 2
    interpolation = [a + half for a, b in itertools.pairwise(train) if b - a == train_every]
    extrapolation = []
    for a, b in itertools.pairwise(train):
        if b - a > train_every:
            extrapolation += [j for j in range(a + half, b, half) if min(j - a, b - j) >= train_every]
    if n_gaps > 0 and not extrapolation:
        raise ValueError(f"gap_len={gap_len} is too short to leave frames far from training frames")
    return FrameSplits(train, interpolation, extrapolation)
