"""Training: scene -> prior -> octree -> pseudo depth -> optimisation -> evaluation, inside one time budget.

``train()`` is what the CLI and the worker call. It writes ``run_dir/checkpoint.pt`` (atomically: temp file +
rename), ``run_dir/report.json`` (config, stages that ran and why, timings, the error-against-run-time
history, final metrics) and ``run_dir/eval/<split>/<frame>.png``.
"""

from __future__ import annotations

import io
import json
import math
import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from voxnerf import hash_kernel
from voxnerf.cameras import camera_rays
from voxnerf.config import TrainConfig
from voxnerf.devices import resolve_device
from voxnerf.errors import TrainingDiverged
from voxnerf.evaluation import EvalView, evaluate_views
from voxnerf.image_io import write_atomic
from voxnerf.losses import color_loss, depth_loss, depth_smoothness_loss
from voxnerf.model import VoxNeRFModel
from voxnerf.octree import SparseVoxelOctree, coverage_octree
from voxnerf.prior import GeometryPrior, load_prior
from voxnerf.pseudo_depth import PriorDepthRenderer
from voxnerf.render import CHECKPOINT
from voxnerf.samplers import RayBundle
from voxnerf.scene import Scene, SceneTransform, load_scene

REPORT = "report.json"
DEFAULT_EVAL_SECONDS_PER_RAY = 1.5e-5
MIN_PRIOR_COVERAGE = 0.05  # below this fraction of training pixels seeing the prior, the report warns
COVERAGE_RAYS = 65_536  # training rays that choose the sampler octree's leaf (voxnerf.octree.coverage_octree)
PAPER_BETA = 0.1  # the paper's log-Huber beta, metres
DEPTH_BETA_PER_SIGMA = 5.0  # default beta = 5 sigma: the paper's 0.1 m for its 2 cm priors, in any unit
ProgressCallback = Callable[[dict], None]


@dataclass
class Stage:
    name: str
    ran: bool
    why: str
    seconds: float = 0.0


@dataclass
class TrainingPixels:
    """Training images and per-pixel caches on the training device.

    images uint8 [N, H, W, 3]; c2w float32 [N, 4, 4] normalised; intr float32 [N, 4] (fl_x, fl_y, cx, cy);
    pseudo_t / hit_t float32 [N, H, W] ray distances (normalised; NaN where invalid), hit bool [N, H, W].
    """

    images: torch.Tensor
    c2w: torch.Tensor
    intr: torch.Tensor
    pseudo_t: torch.Tensor | None = None
    hit_t: torch.Tensor | None = None
    hit: torch.Tensor | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        n, h, w, _ = self.images.shape
        return n, h, w

    def rays(self, img: torch.Tensor, py: torch.Tensor, px: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Rays of the given pixels: origins, dirs [R, 3], normalised units."""
        k = self.intr[img]
        origins, dirs, _ = camera_rays(self.c2w[img], k[:, 0], k[:, 1], k[:, 2], k[:, 3], px, py)
        return origins, dirs


@dataclass
class History:
    """Error against run time: one entry per evaluation."""

    entries: list[dict] = field(default_factory=list)


class Budget:
    """Wall clock of the whole command; ``train_seconds`` excludes time spent in evaluations.

    ``remaining()`` charges everything to ``max_seconds`` except the ``--eval-at`` evaluations (``excluded``):
    those are a benchmark's measuring instrument, and charging them would shorten the run being measured.
    """

    def __init__(self, max_seconds: float | None, previous_train_seconds: float = 0.0) -> None:
        self.start = time.perf_counter()
        self.max_seconds = max_seconds
        self.previous = previous_train_seconds
        self.paused = 0.0
        self.excluded = 0.0

    @property
    def wall(self) -> float:
        return time.perf_counter() - self.start

    @property
    def train_seconds(self) -> float:
        return self.previous + self.wall - self.paused

    def remaining(self) -> float:
        return math.inf if self.max_seconds is None else self.max_seconds - self.previous - self.wall + self.excluded


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _scene_box(scene: Scene, prior: GeometryPrior | None) -> tuple[SceneTransform, np.ndarray]:
    """The normalisation and the scene box [2, 3] (normalised units) from the prior and the cameras.

    Without a prior the box is the cameras' bounding box grown by its largest side in every direction (and at
    least one scene unit), since nothing else tells where the walls are.
    """
    centres = np.stack([f.c2w[:3, 3] for f in scene.frames])
    if prior is not None:
        pts = prior.points
        if len(pts) > 200_000:
            pts = pts[np.random.default_rng(0).choice(len(pts), 200_000, replace=False)]
        pts = np.concatenate([pts, centres])
    else:
        lo, hi = centres.min(0), centres.max(0)
        pad = max(float((hi - lo).max()), 1.0)
        pts = np.stack([lo - pad, hi + pad])
    transform = SceneTransform.fit(pts)
    norm = transform.points_to_normalized(pts)
    aabb = np.stack([norm.min(0), norm.max(0)])
    pad = 0.02 * float((aabb[1] - aabb[0]).max())
    aabb = np.clip(aabb + np.array([[-pad], [pad]]), -1.0, 1.0)
    return transform, aabb


def _training_pixels(scene: Scene, transform: SceneTransform, device: torch.device) -> TrainingPixels:
    idx = scene.train_indices
    sizes = {scene.images[i].shape for i in idx}
    if len(sizes) != 1:
        raise ValueError(f"training images differ in size ({sorted(sizes)}); one size per scene is supported")
    images = torch.from_numpy(np.stack([scene.images[i] for i in idx])).to(device)
    c2w = np.stack([transform.c2w_to_normalized(scene.frames[i].c2w) for i in idx])
    intr = [scene.intrinsics(i) for i in idx]
    return TrainingPixels(
        images,
        torch.from_numpy(c2w).float().to(device),
        torch.tensor([[k.fl_x, k.fl_y, k.cx, k.cy] for k in intr], dtype=torch.float32, device=device),
    )


def _sampler_octree(
    prior: GeometryPrior, pixels: TrainingPixels, model: VoxNeRFModel, cfg: TrainConfig, device: torch.device
) -> tuple[SparseVoxelOctree, str]:
    """The voxnerf sampler's octree over ``prior`` (normalised frame) and a sentence saying how its leaf was
    chosen (``cfg.octree_leaf``: the paper's sigma, or for point clouds the coverage rule on 65,536 training
    rays; mesh priors are sampled at sigma / 3, dense enough for sigma leaves)."""
    points = torch.from_numpy(prior.points).float().to(device)
    if cfg.octree_leaf == "sigma" or prior.kind == "mesh":
        octree = SparseVoxelOctree.from_points(points, prior.sigma)
        why = "octree_leaf: sigma" if cfg.octree_leaf == "sigma" else "mesh prior, sampled densely"
        return octree, (f"voxnerf sampler: {octree.levels} levels, leaf = sigma = {octree.leaf_size:.4g} "
                        f"(normalised; {why})")
    n, h, w = pixels.shape
    gen = torch.Generator(device=device).manual_seed(0)
    flat = torch.randint(0, n * h * w, (min(COVERAGE_RAYS, n * h * w),), generator=gen, device=device)
    rays = model.ray_bundle(*pixels.rays(flat // (h * w), flat % (h * w) // w, flat % w))
    octree, misses = coverage_octree(points, prior.sigma, rays.origins, rays.dirs, rays.near, rays.far)
    tried = ", ".join(f"{s} sigma: {m:.1%}" for s, m in misses.items())
    scale = octree.leaf_size_requested / prior.sigma
    return octree, (f"voxnerf sampler: {octree.levels} levels, leaf {scale:g} sigma = {octree.leaf_size:.4g} "
                    f"(normalised), the smallest that training rays do not slip through (rays missing every "
                    f"leaf: {tried})")


def _per_pixel(
    pixels: TrainingPixels,
    model: VoxNeRFModel,
    fn: Callable[[RayBundle, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    chunk: int = 262_144,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Evaluate ``fn`` ((rays, flat pixel indices [R]) -> (t [R], valid [R])) on every training pixel -> [N, H, W]
    each; t NaN if invalid."""
    n, h, w = pixels.shape
    device = pixels.images.device
    t_all = torch.empty(n * h * w, device=device)
    ok_all = torch.empty(n * h * w, dtype=torch.bool, device=device)
    flat = torch.arange(n * h * w, device=device)
    for i in range(0, n * h * w, chunk):
        f = flat[i : i + chunk]
        img, rem = f // (h * w), f % (h * w)
        origins, dirs = pixels.rays(img, rem // w, rem % w)
        t, ok = fn(model.ray_bundle(origins, dirs), f)
        t_all[i : i + chunk] = torch.where(ok, t, torch.full_like(t, float("nan")))
        ok_all[i : i + chunk] = ok
    return t_all.view(n, h, w), ok_all.view(n, h, w)


def _sample_batch(pixels: TrainingPixels, cfg: TrainConfig, use_patches: bool, gen: torch.Generator):
    """Random pixels plus (optionally) s x s patches: index tensors img, py, px [R] (patches last)."""
    n, h, w = pixels.shape
    device = pixels.images.device
    r = int(cfg.rays_per_batch)
    img = torch.randint(0, n, (r,), generator=gen, device=device)
    py = torch.randint(0, h, (r,), generator=gen, device=device)
    px = torch.randint(0, w, (r,), generator=gen, device=device)
    if use_patches:
        s, p = min(cfg.patch_size, h, w), cfg.smooth_patches
        pi = torch.randint(0, n, (p,), generator=gen, device=device)
        y0 = torch.randint(0, h - s + 1, (p,), generator=gen, device=device)
        x0 = torch.randint(0, w - s + 1, (p,), generator=gen, device=device)
        dy, dx = torch.meshgrid(torch.arange(s, device=device), torch.arange(s, device=device), indexing="ij")
        img = torch.cat([img, pi[:, None].expand(p, s * s).reshape(-1)])
        py = torch.cat([py, (y0[:, None] + dy.reshape(1, -1)).reshape(-1)])
        px = torch.cat([px, (x0[:, None] + dx.reshape(1, -1)).reshape(-1)])
    return img, py, px


def _make_loss_fn(model: VoxNeRFModel, cfg: TrainConfig, beta: float, n_patch_rays: int, patch: int):
    """The differentiable part of a step (field, rendering, losses) as one function of fixed-shape tensors.

    ``beta`` is in scene units. The depth terms compare depths in units of ``beta / 0.1``: for the paper's
    beta = 0.1 m that is metres, and for any other unit (mm, km) the same physical scene gets the same loss,
    so lambda_d keeps its meaning whatever the scene's units and normalisation.
    """
    lam, to_units = cfg.lambda_depth, PAPER_BETA / (beta * model.transform.scale)

    def loss_fn(origins, dirs, starts, ends, target_rgb, target_t, target_ok):
        out = model.render_samples(origins, dirs, starts, ends)
        lc = color_loss(out["rgb"], target_rgb)
        total = lc
        ld = lreg = torch.zeros((), device=origins.device)
        if target_t is not None:
            depth = out["depth"] * to_units
            ld = depth_loss(depth, target_t * to_units, target_ok, PAPER_BETA)
            if n_patch_rays:
                d = depth[-n_patch_rays:].view(-1, patch, patch)
                m = target_ok[-n_patch_rays:].view(-1, patch, patch)
                lreg = depth_smoothness_loss(d, m, cfg.smooth_scales)
            total = lc + lam * (ld + cfg.lambda_smooth * lreg)
        return total, lc, ld, lreg

    return loss_fn


def _save_atomic_torch(obj: dict, path: Path) -> None:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_atomic(path, buffer.getvalue())


def _write_json_atomic(obj: dict, path: Path) -> None:
    write_atomic(path, json.dumps(obj, indent=2, default=float).encode())


def _params_finite(model: VoxNeRFModel) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.field.parameters())


def train(
    scene_dir: str | Path,
    run_dir: str | Path,
    config: TrainConfig,
    *,
    on_progress: ProgressCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
    resume: bool = True,
    progress_bar: bool = True,
) -> dict:
    """Train a model on ``scene_dir`` into ``run_dir`` and return the report (also written to report.json).

    Stops at ``max_iters``, when ``max_seconds`` of wall clock would be exceeded (set-up, octree, pseudo depth
    and the final evaluation included), or when ``should_stop()`` returns True (status "cancelled"; the
    checkpoint is saved). Raises TrainingDiverged if the loss or the weights become NaN/inf; the last good
    checkpoint is kept and the report says why.
    """
    cfg = config.resolved()
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    ckpt_path = run / CHECKPOINT
    previous = torch.load(ckpt_path, map_location="cpu", weights_only=False) if resume and ckpt_path.is_file() else None
    budget = Budget(cfg.max_seconds, previous["train_seconds"] if previous else 0.0)
    device = resolve_device(cfg.device)
    _seed_everything(cfg.seed + (previous["iteration"] if previous else 0))
    stages: list[Stage] = []
    report: dict = {"status": "running", "config": cfg.model_dump(), "device": str(device), "stages": []}
    history = History()
    report["history"] = history.entries

    iteration = 0

    def stage(name: str, ran: bool, why: str, started: float) -> None:
        stages.append(Stage(name, ran, why, time.perf_counter() - started))
        report["stages"] = [vars(s) for s in stages]
        emit(name, iteration)

    last_emit = [0.0]

    def emit(stage_name: str, iteration: int = 0, loss: float | None = None, force: bool = True) -> None:
        now = time.perf_counter()
        if on_progress is None or (not force and now - last_emit[0] < 1.0):
            return
        last_emit[0] = now
        on_progress(_progress_event(stage_name, iteration, loss, cfg, budget, report))

    t0 = time.perf_counter()
    scene = load_scene(scene_dir, downscale=cfg.downscale)
    report["scene"] = scene.summary()
    stage("load_scene", True, f"{len(scene.frames)} frames, {len(scene.train_indices)} for training", t0)

    t0 = time.perf_counter()
    prior = None
    needs_prior = cfg.sampler == "voxnerf" or cfg.depth_loss
    if scene.prior_path is not None:
        prior = load_prior(scene.prior_path, scene.prior_sigma, seed=cfg.seed)
        why = "sets the scene box" + (" and guides sampling / depth" if needs_prior else " only (not needed else)")
        stage("prior", True, f"{prior.kind} prior, sigma {prior.sigma:.4g} "
              f"({'estimated' if prior.sigma_estimated else 'given'}); {why}", t0)
        report["prior"] = prior.summary()
    else:
        stage("prior", False, "the scene has no prior", t0)
    if needs_prior and prior is None:
        report.setdefault("warnings", []).append(
            f"sampler {cfg.sampler!r}{' and the depth loss' if cfg.depth_loss else ''} need a prior; "
            "the scene has none, so sampling falls back to the occupancy grid and no depth loss is used"
        )

    t0 = time.perf_counter()
    if device.type != "cpu":
        stage("hash_kernel", False, f"on {device.type} the hash encoding stays in PyTorch", t0)
    elif not cfg.hash_kernel:
        stage("hash_kernel", False, "disabled (--no-hash-kernel): the hash encoding stays in PyTorch", t0)
    elif hash_kernel.available():
        stage("hash_kernel", True, "the hash encoding runs in its C kernel (voxnerf/hashgrid.c; built once, cached)",
              t0)
    else:
        stage("hash_kernel", False, f"C kernel unavailable ({hash_kernel.unavailable_reason()}): the hash encoding "
              "stays in PyTorch", t0)

    transform, aabb = _scene_box(scene, prior)
    prior_n = prior.transformed(np.asarray(transform.center), transform.scale) if prior is not None else None

    model = VoxNeRFModel.create(cfg, transform, torch.from_numpy(aabb).float(), None, device)
    if prior_n is not None and cfg.sampler != "uniform":
        model.grid.seed_from_points(torch.from_numpy(prior_n.points).float().to(device))
    # fused: one pass over each parameter per step instead of one per Adam operation; on this CPU it makes the
    # update of a 2^19-entry table about 10x cheaper (benchmarks/optimizer_step.py).
    optimizer = torch.optim.Adam(model.field.parameters(), lr=cfg.lr, eps=1e-15, fused=True)
    if previous is not None:
        model.field.load_state_dict(previous["model"]["field"])
        model.grid.load_state_dict(previous["model"]["grid"])
        optimizer.load_state_dict(previous["optimizer"])
        iteration = int(previous["iteration"])
        history.entries.extend(previous["history"])
        report["resumed_from_iteration"] = iteration

    pixels = _training_pixels(scene, transform, device)
    t0 = time.perf_counter()
    octree = None
    if cfg.sampler == "voxnerf" and prior_n is not None:
        octree, why = _sampler_octree(prior_n, pixels, model, cfg, device)
        model.octree = octree
        report["octree"] = octree.summary()
        stage("octree", True, why, t0)
    else:
        why = "no prior" if prior_n is None else f"sampler {cfg.sampler!r} does not use it"
        stage("octree", False, why, t0)

    t0 = time.perf_counter()
    use_depth = cfg.depth_loss and prior_n is not None
    if use_depth:
        # Leaves of the prior's sigma (the paper's) give the most accurate point-cloud depths, whatever leaf
        # the sampler's octree settled on.
        depth_svo = octree if octree is not None and octree.leaf_size == prior_n.sigma else (
            SparseVoxelOctree.from_points(torch.from_numpy(prior_n.points).float().to(device), prior_n.sigma))
        renderer = PriorDepthRenderer(prior_n, depth_svo)
        pixels.pseudo_t, _ = _per_pixel(
            pixels, model, lambda rays, _: renderer.ray_distance(rays.origins, rays.dirs, rays.near, rays.far)
        )
        valid = float(torch.isfinite(pixels.pseudo_t).float().mean())
        if valid < MIN_PRIOR_COVERAGE:
            report.setdefault("warnings", []).append(
                f"{scene.prior_path.name}: only {valid:.1%} of training pixels see the prior; check its units, "
                "placement and prior_sigma"
            )
        stage("pseudo_depth", True, f"depth loss: prior ray-cast for every training pixel ({valid:.1%} valid)", t0)
    else:
        why = "depth loss disabled" if not cfg.depth_loss else "no prior to render depth from"
        stage("pseudo_depth", False, why, t0)

    t0 = time.perf_counter()
    if octree is not None:
        # The pseudo depth, where there is one, tells the search where to stop first (same result, less work).
        hint = pixels.pseudo_t.view(-1) if pixels.pseudo_t is not None else None
        pixels.hit_t, pixels.hit = _per_pixel(
            pixels, model, lambda rays, index: octree.first_hit(
                rays.origins, rays.dirs, rays.near, rays.far, t_hint=None if hint is None else hint[index]
            )
        )
        stage("first_hit_cache", True, f"octree first hit of every training pixel "
              f"({float(pixels.hit.float().mean()):.1%} hit)", t0)
    else:
        stage("first_hit_cache", False, "no octree", t0)

    use_patches = use_depth and cfg.smooth_patches > 0 and cfg.lambda_smooth > 0
    patch = min(cfg.patch_size, pixels.shape[1], pixels.shape[2])
    n_patch_rays = cfg.smooth_patches * patch * patch if use_patches else 0
    beta = cfg.depth_beta or (DEPTH_BETA_PER_SIGMA * prior.sigma if prior is not None else PAPER_BETA)
    report["depth_beta"] = beta if use_depth else None
    loss_fn = _make_loss_fn(model, cfg, beta, n_patch_rays, patch)
    step_fn = loss_fn
    t0 = time.perf_counter()
    if cfg.compile:
        step_fn = torch.compile(loss_fn, dynamic=False)
    else:
        stage("compile", False, "disabled (--no-compile)", t0)
    sampler = model.sampler()
    gen = torch.Generator(device=device)
    gen.manual_seed(cfg.seed + iteration)

    eval_views = eval_views_of(scene, transform)
    next_progress_eval = budget.train_seconds + cfg.eval_every_s
    pending_full = sorted(t for t in cfg.eval_at if t > budget.train_seconds)
    last_ckpt = time.perf_counter()
    # Final-evaluation cost per ray: a guess until a progress evaluation (after the first, which compiles)
    # measures it.
    eval_seconds_per_ray = DEFAULT_EVAL_SECONDS_PER_RAY
    evals_done = 0
    status = "succeeded"
    compile_pending = cfg.compile
    pbar = tqdm(total=cfg.max_iters, initial=iteration, disable=not progress_bar, file=sys.stderr,
                desc="train", dynamic_ncols=True)
    last_loss = float("nan")

    def save_checkpoint() -> None:
        if not _params_finite(model):
            raise TrainingDiverged(f"weights became NaN/inf before iteration {iteration}")
        _save_atomic_torch(_checkpoint(model, optimizer, iteration, budget, history, scene), ckpt_path)

    def final_eval_reserve() -> float:
        if not cfg.final_eval:
            return 0.0
        rays = sum(v.rays for views in eval_views.values() for v in views)
        return 1.5 * eval_seconds_per_ray * rays + 2.0

    try:
        while True:
            if cfg.max_iters is not None and iteration >= cfg.max_iters:
                break
            if budget.remaining() - final_eval_reserve() <= 0:
                break
            if should_stop is not None and should_stop():
                status = "cancelled"
                break
            if budget.train_seconds >= next_progress_eval or (pending_full and budget.train_seconds >= pending_full[0]):
                full = bool(pending_full) and budget.train_seconds >= pending_full[0]
                if full:
                    pending_full.pop(0)
                spent, per_ray = _progress_eval(model, eval_views, cfg, history, iteration, last_loss, budget, full)
                evals_done += 1
                if evals_done > 1 or not cfg.compile:
                    eval_seconds_per_ray = per_ray
                budget.paused += spent
                if full:
                    budget.excluded += spent
                next_progress_eval = budget.train_seconds + cfg.eval_every_s
                emit("train", iteration, last_loss)

            lr = cfg.lr * 0.1 ** (iteration / cfg.lr_decay_iters)
            for group in optimizer.param_groups:
                group["lr"] = lr
            img, py, px = _sample_batch(pixels, cfg, use_patches, gen)
            origins, dirs = pixels.rays(img, py, px)
            rays = model.ray_bundle(origins, dirs)
            if pixels.hit_t is not None:
                rays.hit_t, rays.hit = pixels.hit_t[img, py, px], pixels.hit[img, py, px]
            with torch.no_grad():
                starts, ends = sampler(rays, True)
            target_rgb = pixels.images[img, py, px].float() / 255.0
            target_t = target_ok = None
            if pixels.pseudo_t is not None:
                target_t = pixels.pseudo_t[img, py, px]
                target_ok = torch.isfinite(target_t)
            total, lc, ld, lreg = step_fn(rays.origins, rays.dirs, starts, ends, target_rgb, target_t, target_ok)
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            last_loss = float(total.detach())
            if not math.isfinite(last_loss):
                raise TrainingDiverged(
                    f"loss became {last_loss} at iteration {iteration} (colour {float(lc.detach()):.4g}, "
                    f"depth {float(ld.detach()):.4g}, smoothness {float(lreg.detach()):.4g})"
                )
            optimizer.step()
            iteration += 1
            pbar.update(1)
            if compile_pending:
                compile_pending = False
                stage("compile", True, "torch.compile of the training step (time of the first step)", t0)
            # The grid drives the occgrid sampler; for voxnerf it only serves rays that miss the octree.
            every = cfg.occgrid_update_every * (1 if cfg.sampler == "occgrid" or octree is None else 4)
            if cfg.sampler != "uniform" and iteration % every == 0:
                # Eager, the update (65 K-330 K points) cost as much as 15 training steps on redkitchen.
                density = model.compiled_density() if cfg.compile else model.field.density
                model.grid.update(density, warmup=iteration <= 2 * every)
            if iteration % 50 == 0:
                pbar.set_postfix(loss=f"{last_loss:.4g}", lr=f"{lr:.2g}")
            if time.perf_counter() - last_ckpt >= cfg.checkpoint_every_s:
                save_checkpoint()
                last_ckpt = time.perf_counter()
            emit("train", iteration, last_loss, force=False)
    except TrainingDiverged as exc:
        pbar.close()
        report.update(status="diverged", error=str(exc), iteration=iteration, checkpoint_kept=ckpt_path.is_file())
        _write_json_atomic(report, run / REPORT)
        raise TrainingDiverged(
            f"{exc}; {'last good checkpoint kept at ' + str(ckpt_path) if ckpt_path.is_file() else 'no checkpoint yet'}"
        ) from None
    pbar.close()
    if compile_pending:
        stage("compile", False, "no training step ran", t0)
    train_seconds = budget.train_seconds
    stages.append(Stage("train", iteration > 0, f"{status} at iteration {iteration}", train_seconds))
    report["stages"] = [vars(s) for s in stages]
    save_checkpoint()

    t0 = time.perf_counter()
    if cfg.final_eval and status == "succeeded" and eval_views:
        emit("final_eval", iteration, last_loss)
        metrics = evaluate_views(model, eval_views, cfg, out_dir=run / "eval")
        history.entries.append({
            "elapsed_s": round(train_seconds, 3), "wall_s": round(budget.wall, 3), "iteration": iteration,
            "loss": last_loss, "final": True, "psnr": {k: v["psnr"] for k, v in metrics.items()},
            "progress_psnr": _progress_views_psnr(metrics, eval_views, cfg.eval_views),
        })
        report["metrics"] = metrics
        stage("final_eval", True, f"all views of splits {sorted(eval_views)}", t0)
    else:
        why = ("disabled" if not cfg.final_eval else "run cancelled" if status == "cancelled"
               else "the scene has no evaluation split")
        stage("final_eval", False, why, t0)
    report.update(status=status, iteration=iteration, train_seconds=round(train_seconds, 3),
                  wall_seconds=round(budget.wall, 3),
                  throughput=_throughput(cfg, iteration, stages, use_patches, n_patch_rays))
    _write_json_atomic(report, run / REPORT)
    emit("done", iteration, last_loss)
    return report


def _throughput(cfg: TrainConfig, iterations: int, stages: list[Stage], patches: bool, patch_rays: int) -> dict:
    train = next((s.seconds for s in stages if s.name == "train"), 0.0)
    compile_s = next((s.seconds for s in stages if s.name == "compile" and s.ran), 0.0)
    rays_per_step = int(cfg.rays_per_batch) + (patch_rays if patches else 0)
    rays = rays_per_step * iterations
    seconds = max(train - compile_s, 1e-9)
    return {"rays_per_step": rays_per_step, "rays_per_s": rays / seconds,
            "samples_per_s": rays * cfg.samples_per_ray / seconds, "seconds_excluding_compile": seconds}


def eval_views_of(scene: Scene, transform: SceneTransform, names: list[str] | None = None) -> dict[str, list[EvalView]]:
    """The views of every evaluation split of a loaded scene, posed in normalised units (a split listing the
    same frames as an earlier one is left out), or of the splits ``names``."""
    views: dict[str, list[EvalView]] = {}
    seen: list[list[int]] = []
    for name in names or scene.eval_split_names:
        if names is None and scene.splits[name] in seen:  # e.g. test_filenames repeating an eval split: evaluate once
            continue
        seen.append(scene.splits[name])
        views[name] = [
            EvalView(
                Path(scene.frames[i].file_path).stem,
                torch.from_numpy(transform.c2w_to_normalized(scene.frames[i].c2w)).float(),
                scene.intrinsics(i),
                torch.from_numpy(scene.images[i]),
            )
            for i in scene.splits[name]
        ]
    return views


def _progress_eval(
    model: VoxNeRFModel,
    views: dict[str, list[EvalView]],
    cfg: TrainConfig,
    history: History,
    iteration: int,
    loss: float,
    budget: Budget,
    full: bool,
) -> tuple[float, float]:
    """Evaluate a few views per split (all of them when ``full``); returns (seconds spent, seconds per ray)."""
    t0 = time.perf_counter()
    elapsed, wall = budget.train_seconds, budget.wall
    subset = {name: (v if full else _spread(v, cfg.eval_views)) for name, v in views.items()}
    metrics = evaluate_views(model, subset, cfg, out_dir=None, lpips=full)
    spent = time.perf_counter() - t0
    rays = sum(v.rays for vs in subset.values() for v in vs)
    entry = {
        "elapsed_s": round(elapsed, 3), "wall_s": round(wall, 3), "iteration": iteration,
        "loss": loss if math.isfinite(loss) else None, "psnr": {k: m["psnr"] for k, m in metrics.items()},
    }
    if full:
        entry["full"] = True
        entry["ssim"] = {k: m["ssim"] for k, m in metrics.items()}
        entry["progress_psnr"] = _progress_views_psnr(metrics, views, cfg.eval_views)
    history.entries.append(entry)
    return spent, spent / max(rays, 1)


def _progress_views_psnr(metrics: dict, views: dict[str, list[EvalView]], n: int) -> dict[str, float]:
    """Mean PSNR (dB) per split over the views a progress evaluation uses, from a full evaluation's per-view
    ``metrics``: so that one curve over the same views runs through progress and full evaluations alike."""
    return {
        split: float(np.mean([m["views"][i]["psnr"] for i in _spread(list(range(len(views[split]))), n)]))
        for split, m in metrics.items()
    }


def _spread(views: list, n: int) -> list:
    if len(views) <= n:
        return views
    idx = np.linspace(0, len(views) - 1, n).round().astype(int)
    return [views[i] for i in idx]


def _progress_event(stage: str, iteration: int, loss: float | None, cfg: TrainConfig, budget: Budget,
                    report: dict) -> dict:
    fractions = []
    if cfg.max_iters:
        fractions.append(iteration / cfg.max_iters)
    if cfg.max_seconds:
        fractions.append((budget.previous + budget.wall) / cfg.max_seconds)
    progress = min(1.0, max(fractions)) if fractions else 0.0
    eta = budget.wall * (1 - progress) / progress if 0 < progress < 1 else None
    return {
        "stage": stage, "iteration": iteration, "max_iters": cfg.max_iters, "elapsed_s": budget.train_seconds,
        "progress": 1.0 if stage == "done" else progress, "eta_s": eta,
        "loss": loss if loss is not None and math.isfinite(loss) else None,
        "history": list(report["history"]), "stages": list(report["stages"]),
    }


def _checkpoint(model: VoxNeRFModel, optimizer, iteration: int, budget: Budget, history: History,
                scene: Scene) -> dict:
    first = scene.intrinsics(scene.train_indices[0])
    return {
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "iteration": iteration,
        "train_seconds": budget.train_seconds,
        "history": history.entries,
        "default_intrinsics": first.as_dict(),
        "depth_unit_scale": scene.depth_unit_scale,
        "scene_dir": str(scene.root),
    }
