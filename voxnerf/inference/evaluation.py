"""Evaluation of a model on held-out views: renders, PSNR / SSIM / LPIPS, and the rendered PNGs."""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import torch

from voxnerf.cameras.rays import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.data.image_io import encode_png, write_atomic
from voxnerf.inference.fast_path import FAST
from voxnerf.inference.metrics import LPIPS, LPIPS_UNAVAILABLE, evaluate_images, half_image_pairs
from voxnerf.inference.render import PIXEL_RAYS, pixel_rays, render_normalized, resolved_render_path
from voxnerf.model.voxnerf_model import VoxNeRFModel


class EvaluationStopped(Exception):
    """``should_stop()`` said yes between two views of :func:`evaluate_views`."""


@dataclass
class EvalView:
    """A held-out view: name (unique in its split, see :func:`view_names`), c2w [4, 4] normalised units,
    intrinsics, ground truth uint8 [H, W, 3].

    The intrinsics keep the frame's lens: the view renders through it, so a distorted camera is scored against
    its own distorted ground-truth image (no image is ever resampled).
    """

    name: str
    c2w: torch.Tensor
    intrinsics: Intrinsics
    image: torch.Tensor

    @property
    def rays(self) -> int:
        return self.intrinsics.width * self.intrinsics.height


def view_names(file_paths: Sequence[str], frame_indices: Sequence[int]) -> list[str]:
    """The names of a split's views, one per frame: the file's stem, made unique within the split.

    A stem that several frames share (``a/frame1.png``, ``b/frame1.png``) gets each frame's index in the scene
    appended (``frame1-3``, ``frame1-8``; its position in the split when the split lists a frame twice), again
    until no two names are equal (an appended name may meet another frame's own stem), so the renders
    ``<split>/<name>.png`` never overwrite each other.
    """
    names = [PurePosixPath(path).stem for path in file_paths]
    keys = list(frame_indices) if len(set(frame_indices)) == len(names) else list(range(len(names)))
    while True:
        counts = Counter(names)
        if all(n == 1 for n in counts.values()):
            return names
        names = [f"{name}-{key}" if counts[name] > 1 else name for name, key in zip(names, keys, strict=True)]


@functools.lru_cache(maxsize=1)
def lpips_model() -> LPIPS | None:
    """The LPIPS(AlexNet) network on the CPU, or None when its weights are not installed."""
    return LPIPS.load("cpu")


def _corrections_note(model: VoxNeRFModel) -> dict[str, str]:
    """What the model's per-image corrections did to the views (nothing for a model without them)."""
    note = {}
    if model.pose_refinement is not None:
        note["poses"] = "given, moved by the pose corrections of the nearest training cameras"
    if model.appearance is not None:
        note["colours"] = "corrected as the nearest training cameras' images were"
    return note


LpipsChoice = tuple[LPIPS | None, str | None]  # the network to score with (None: none) and why there is none


def _lpips_of(views: dict[str, list[EvalView]], asked: bool, half_image: bool) -> tuple[LpipsChoice, LpipsChoice]:
    """The LPIPS network for the views and for their right halves (the half-image protocol), each with the note
    saying why it is left out: not asked for, weights not installed, or an image smaller than AlexNet's layers
    accept (31 pixels; a view wide enough may have a half too narrow, as a narrow portrait view does)."""
    lp = lpips_model() if asked else None
    note = LPIPS_UNAVAILABLE if asked and lp is None else None
    every = [v.intrinsics for split_views in views.values() for v in split_views]
    smallest = min((min(k.width, k.height) for k in every), default=0)
    if lp is not None and smallest < lp.min_size:  # AlexNet's layers need 31 pixels: skip, say why
        lp, note = None, f"LPIPS needs images of at least {lp.min_size}x{lp.min_size} pixels"
    smallest_half = min((min(k.height, k.width - k.width // 2) for k in every), default=0)
    if half_image and lp is not None and smallest_half < lp.min_size:
        return (lp, note), (None, f"LPIPS needs images of at least {lp.min_size}x{lp.min_size} pixels, and the "
                                  f"right half of some view is {smallest_half} pixels across")
    return (lp, note), (lp, None)


def evaluate_views(
    model: VoxNeRFModel,
    views: dict[str, list[EvalView]],
    cfg: TrainConfig,
    out_dir: Path | None = None,
    lpips: bool = True,
    path: str = "auto",
    should_stop: Callable[[], bool] | None = None,
    half_image: bool = False,
) -> dict[str, dict]:
    """Render every view of every split (on the render ``path``, see :func:`voxnerf.inference.render.render_normalized`)
    and score it.

    Returns ``{split: {"psnr", "ssim", "lpips" (None if unavailable or not asked), "lpips_note"?, "renderer",
    "views": [{"name", "psnr", "ssim", "lpips"}]}}`` (means at the top; ``renderer`` says which path rendered
    them); LPIPS is also left out, with a note saying why, when a view is smaller than its network accepts.
    A model with pose refinement adds ``"poses"``, saying how the views' poses were moved, and one with per-image
    appearance ``"colours"``.
    ``half_image`` adds ``"half": {"psnr", "ssim", "lpips"}``, the means of the half-image protocol
    (:func:`voxnerf.inference.metrics.half_image_pairs`: colour affine fitted on each view's left half, scored on its
    right); its LPIPS is left out, with ``"half_lpips_note"`` saying why, when a half is too small for the network
    (a narrow portrait view).
    Writes ``out_dir/<split>/<name>.png`` when ``out_dir`` is given. Raises EvaluationStopped when
    ``should_stop()`` (asked before each view) returns True.
    """
    (lp, note), (half_lp, half_note) = _lpips_of(views, lpips, half_image)
    results: dict[str, dict] = {}
    for split, split_views in views.items():
        preds, gts = [], []
        for view in split_views:
            if should_stop is not None and should_stop():
                raise EvaluationStopped()
            rgb = render_normalized(model, view.c2w, view.intrinsics, ("rgb",), path=path)["rgb"]
            rgb = rgb.float().cpu().clamp(0.0, 1.0)
            preds.append(rgb)
            gts.append(view.image.float() / 255.0)
            if out_dir is not None:
                (out_dir / split).mkdir(parents=True, exist_ok=True)
                write_atomic(out_dir / split / f"{view.name}.png", encode_png(rgb.numpy()))
        scores = evaluate_images(preds, gts, lp)
        mean = scores["mean"]
        renderer = (FAST.describe(model.device) if resolved_render_path(path, model.device) == "fast"
                    else "full: every sample of every ray")
        if len(pixel_rays(model, ("rgb",))) > 1:
            renderer += f"; antialiased: {len(PIXEL_RAYS)} rays per pixel"
        entry = {"psnr": mean["psnr"], "ssim": mean["ssim"], "lpips": mean["lpips"], "renderer": renderer, "views": [
            {"name": v.name, "psnr": scores["psnr"][i], "ssim": scores["ssim"][i],
             "lpips": None if scores["lpips"] is None else scores["lpips"][i]}
            for i, v in enumerate(split_views)
        ]}
        entry |= _corrections_note(model)
        if half_image:
            halves = [half_image_pairs(p, g) for p, g in zip(preds, gts, strict=True)]
            entry["half"] = evaluate_images([p for p, _ in halves], [g for _, g in halves], half_lp)["mean"]
            if half_note is not None:
                entry["half_lpips_note"] = half_note
        if note is not None:
            entry["lpips_note"] = note
        results[split] = entry
    return results
