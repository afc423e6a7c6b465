"""Training configuration: one pydantic model nested by component (run, model, sampling, loss, schedule,
corrections, evaluation), with presets for a CPU and for the paper's GPU setting as data.

Every setting has one name in its component (``schedule.lr``, ``sampling.n_importance``); the names are unique
across components, so the flat name alone (``lr``, ``n_importance``) says which one is meant. :class:`TrainConfig`
accepts either form (``TrainConfig(lr=0.02)``, ``TrainConfig(schedule={"lr": 0.02})``,
``TrainConfig(**{"schedule.lr": 0.02})``), which keeps every earlier config, checkpoint and command working;
:meth:`TrainConfig.flat` gives the flat form report.json and the service store, and :data:`FIELD_SECTIONS` maps
each flat name to its component.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator
from pydantic.fields import FieldInfo

Preset = Literal["cpu", "paper"]
SamplerName = Literal["auto", "voxnerf", "occgrid", "uniform"]
DepthSource = Literal["auto", "sensor", "prior", "none"]
LrSchedule = Literal["iterations", "budget"]
Appearance = Literal["auto", "none", "affine"]
PoseRefinementMode = Literal["auto", "none", "so3xr3"]
MAX_LR = 1.0  # Adam steps of this size already throw a hash grid's features far outside their useful range

# Values that differ between presets, by component. "paper" is the paper's GPU setting (4096 rays, 128 + 128
# samples, 2^19 hash tables); "cpu" trades samples per ray (8 + 4) and table size for steps per second, chosen with
# the samples-per-ray sweep (benchmarks/samples_sweep.py; docs/benchmarks.md, 'Samples per ray'). "cpu" is the
# default on every device: on a GPU "paper" wins interpolation but not extrapolation (docs/cuda.md).
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "cpu": {
        "schedule": {"rays_per_batch": 2048, "lr_decay_iters": 20_000},
        "sampling": {"n_importance": 8, "n_rest": 4},
        "model": {"hash_levels": 12, "hash_features": 2, "hash_log2_size": 17, "hash_max_resolution": 1024,
                  "hidden_dim": 64},
    },
    "paper": {
        "schedule": {"rays_per_batch": 4096, "lr_decay_iters": 30_000},
        "sampling": {"n_importance": 128, "n_rest": 128},
        "model": {"hash_levels": 16, "hash_features": 2, "hash_log2_size": 19, "hash_max_resolution": 2048,
                  "hidden_dim": 64},
    },
}
# Rays per pass of the full render path by device type, where eval_chunk is not set: on a GPU one pass of 32,768
# rays keeps it busy (an H200 evaluated redkitchen's 55 views in 11.1 s in such passes, in 17.9 s in 4,096-ray
# ones: docs/cuda.md); a CPU keeps the 4,096 it always had.
EVAL_CHUNKS = {"cpu": 4096, "cuda": 32_768}
STRICT = {"extra": "forbid", "allow_inf_nan": False}
# Who may set a setting besides the Python API and ``voxnerf train --set``: a job's REST options (JOB, also the CLI's
# named flags), the worker's deployment settings (WORKER: where a job trains, how often it saves, how long its
# eval_at evaluations may take). Unmarked settings are tuned values a job should not move by accident (the presets
# own the model's size and the batch; loss weights, learning rates and the samplers' knobs were chosen by
# measurement, docs/engine.md; evaluation views, background and the final evaluation stay fixed so jobs compare).
JOB = {"audience": "job"}
WORKER = {"audience": "worker"}


class _Section(BaseModel):
    """A component of the config. A field whose default is None takes the preset's value (see
    :meth:`TrainConfig.resolved`); ``eval_chunk`` alone takes the rendering device's
    (:meth:`EvaluationConfig.chunk_on`)."""

    model_config = STRICT


class RunConfig(_Section):
    """How the command runs: its limits, device, seed, compilation, kernels, caches and checkpoints."""

    max_seconds: float | None = Field(json_schema_extra=JOB, default=None, gt=0,
                                      description="seconds of training: the loop's steps, progress evaluations and "
                                      "checkpoints (set-up, compilation and the final evaluation come on top)")
    max_iters: int | None = Field(json_schema_extra=JOB, default=None, gt=0)
    downscale: int = Field(json_schema_extra=JOB, default=1, ge=1, le=16)
    device: str = Field(default="auto", json_schema_extra=WORKER)
    seed: int = Field(default=0, json_schema_extra=JOB)
    compile: bool = Field(default=True, json_schema_extra=JOB)
    hash_kernel: bool = Field(json_schema_extra=JOB,
        default=True,
        description="on the CPU, run the hash encoding through the C kernel of voxnerf/model/hash_kernel.py where it "
        "builds (the same features, a cheaper backward); False keeps the pure-PyTorch encoding",
    )
    setup_cache: bool = Field(
        default=True,
        description="load the set-up's per-pixel ray casts (the prior's depth, the octree's first hits) from "
        "$VOXNERF_CACHE/setup when an earlier run cast the same rays against the same geometry with the same code",
    )
    checkpoint_every_s: float = Field(json_schema_extra=WORKER, default=60.0, gt=0)

    @field_validator("device")
    @classmethod
    def _device(cls, value: str) -> str:
        if value not in ("auto", "cpu") and not value.startswith("cuda"):
            raise ValueError("device must be auto, cpu or cuda[:N]")
        return value

class ModelConfig(_Section):
    """The radiance field (paper III-B): the hash encoding, the MLPs, and the colour behind every ray."""

    hash_levels: int | None = Field(default=None, ge=1, le=32)
    hash_features: int | None = Field(default=None, ge=1, le=8)
    hash_log2_size: int | None = Field(default=None, ge=10, le=24)
    hash_max_resolution: int | None = Field(default=None, ge=16)
    hidden_dim: int | None = Field(default=None, ge=8)
    sh_bands: int = Field(
        default=4, ge=1, le=4,
        description="spherical-harmonic bands of the direction encoding: 4 (16 coefficients, the paper's) to 1 "
        "(a constant: colour independent of the viewing direction)",
    )
    background: tuple[float, float, float] | Literal["training_mean"] = Field(
        default="training_mean",
        description="colour behind the last sample of every ray in renders (sRGB in [0, 1]), or 'training_mean': "
        "the mean colour of the training images, fixed when training starts. It is what a view shows where it "
        "looks at space no training view saw (docs/benchmarks.md, 'The tuning suite')",
    )
    render_background: Literal["colour", "nearest_seen"] = Field(
        default="nearest_seen",
        description="what a rendered ray shows behind its last sample: 'colour' the background; 'nearest_seen' "
        "the colour the training images show nearest to where the ray meets the prior (the voxnerf sampler's "
        "window centre), pooled at set-up from the training pixels at their depth targets "
        "(voxnerf/model/colour_prior.py), and the background where the ray misses the prior or the run samples "
        "without the octree. Training rays keep train_background. The default won on the tuning suite's halves "
        "(docs/benchmarks.md, 'What a view shows where no training view looked')",
    )
    nearest_seen_weight: float = Field(
        default=1.0, ge=0.0, le=1.0,
        description="with render_background 'nearest_seen', the weight of the colour seen nearest to a rendered "
        "ray's prior hit in what the ray shows there, the rest the background colour: the guess for a surface no "
        "training view saw, shrunk towards the training images' mean; 1 shows the nearest seen colour alone. 0.75 "
        "tied with 1 on the tuning suite's halves (docs/benchmarks.md, 'What a view shows where no training view "
        "looked')",
    )
    antialias: bool = Field(
        default=True,
        description="render each pixel's colour as the weighted mean of five rays through it, its centre (weight "
        "1/3) and the centres of its four quarters (1/6 each), as a camera averages over its pixel's area: five "
        "times the rays of a colour render; depth and opacity stay the centre ray's. false renders the centre ray "
        "alone. Training rays are unchanged. The default won on the tuning suite's halves (docs/benchmarks.md, "
        "'Antialiased renders')",
    )
    cone_radius: Annotated[float, Field(ge=0.0, le=0.1)] | Literal["auto"] | None = Field(
        default=None,
        description="read the field over each pixel's cone instead of at points (Zip-NeRF's feature downweighting): "
        "a sample's footprint radius is its distance times this (radians), 'auto' a training pixel's (1 / (sqrt(3) "
        "f), fixed when training starts); None reads points",
    )

class SamplingConfig(_Section):
    """The samplers (paper III-C): which one, samples per ray, the octree's leaf and carving, the occupancy grid."""

    sampler: SamplerName = Field(
        default="auto", json_schema_extra=JOB,
        description="'voxnerf' (the paper's window around the prior's first hit), 'occgrid' (an occupancy grid, "
        "seeded from the prior where there is one), 'uniform', or 'auto': 'voxnerf' unless the set-up's window "
        "check finds the prior's first hit wrong on more than 6 % of the rays with depth, then 'occgrid' "
        "(fixed at set-up; report.json's window_check stage says which and why); the VoxNeRF sampler against the "
        "seeded grid with everything else equal, per scene at 300 s: docs/benchmarks.md, 'The sampler alone'",
    )

    @property
    def may_use_window(self) -> bool:
        """Whether the set-up builds the VoxNeRF sampler's octree: for ``voxnerf``, and for ``auto`` until its
        choice (the window check needs the octree's first hits)."""
        return self.sampler in ("auto", "voxnerf")

    prior_file: bool = Field(
        default=True,
        description="use the scene's prior file; False trains as if the scene had none (the prior is then fused from "
        "the training frames' depth maps where they have them, docs/engine.md)",
    )
    n_importance: int | None = Field(json_schema_extra=JOB, default=None, ge=1)
    n_rest: int | None = Field(json_schema_extra=JOB, default=None, ge=1)
    octree_leaf: Literal["coverage", "sigma"] = Field(
        default="coverage",
        description="sampler octree leaf: 'sigma' (the paper) or, for point-cloud priors, the smallest multiple "
        "of sigma (1-3) that the training rays do not slip through (mesh priors always use sigma)",
    )
    octree_carving: bool = Field(
        default=True,
        description="remove the sampler octree's leaves that the training frames' sensor depth shows empty (rays "
                    "cross them well before their measured depth and no measured point lies in them): outliers and "
                    "noise beyond silhouettes, where a ray would stop short of its surface (voxnerf.prior.carving; "
                    "docs/engine.md, 'Pipeline', step 6)",
    )
    window_centre: Literal["entry", "surface"] = Field(
        default="surface",
        description="where the voxnerf sampler centres its window on a ray: 'surface', where the ray passes the "
        "mean of the prior's points around its first occupied leaf, or 'entry', that leaf's entry (the paper's z, "
        "in front of the surface by up to a leaf diagonal) (voxnerf.model.samplers.WINDOW_CENTRES; docs/engine.md, "
        "'Samplers'; chosen on the suite's halves, docs/benchmarks.md)",
    )
    window_width: float = Field(
        default=1.0, gt=0.0,
        description="the voxnerf sampler's window in multiples of the paper's: half-width 3 sqrt(3) v and "
        "Gaussian std sqrt(3) v around the window's centre, v the octree's leaf (docs/engine.md, 'Samplers')",
    )
    occgrid_seed: bool = Field(
        default=True,
        description="start the occupancy grid from the prior's cells; False starts it all occupied and lets it "
        "learn from the field's density alone (nerfacc's grid, the paper's baseline)",
    )
    occgrid_resolution: int = Field(default=64, ge=8)
    occgrid_update_every: int = Field(default=32, ge=1)
    octree_misses: Literal["auto", "gather", "mask"] = Field(
        default="auto",
        description="how the voxnerf sampler's rays that miss the octree get the occupancy grid's samples: "
        "'gather' samples only those rays (the hit mask is read on the host: a device sync per batch on a GPU), "
        "'mask' samples every ray and keeps the missing rays' samples (fixed shapes, no sync); 'auto': gather on "
        "a CPU, mask on a GPU (voxnerf.model.samplers.octree_misses_on; docs/cuda.md)",
    )

    @property
    def samples_per_ray(self) -> int:
        return int(self.n_importance) + int(self.n_rest)

class LossConfig(_Section):
    """The loss (paper III-D): the depth term and its target, smoothness, distortion, prior rays, and the colour
    behind each training ray."""

    depth_loss: bool = Field(json_schema_extra=JOB, default=True,
                             description="False leaves the depth terms out (as depth_source 'none')")
    depth_source: DepthSource = Field(json_schema_extra=JOB,
        default="auto",
        description="what the depth loss compares with: 'sensor' (the training frames' depth maps where valid, "
        "the prior's depth elsewhere), 'prior' (the prior's depth only), 'none'; 'auto' is 'sensor' when the "
        "training frames have depth maps, else 'prior' when there is a prior, else 'none'",
    )
    lambda_depth: float = Field(
        default=0.3, ge=0,
        description="lambda_d of the paper's total loss (no value in the paper; docs/engine.md, 'Losses')",
    )
    lambda_smooth: float = Field(
        default=0.01, ge=0, description="weight of the smoothness term inside lambda_d's bracket (paper: 1)"
    )
    depth_beta: float | None = Field(
        default=None, gt=0, description="log-Huber beta in scene units; default 5 x the prior's sigma (paper: 0.1 m), "
        "and for sensor depth 5 x the depth noise measured at that depth"
    )
    smooth_patches: int = Field(json_schema_extra=JOB,
        default=0,
        ge=0,
        description="s x s patches per batch for the smoothness term; 0 (the default) leaves the term out "
        "(docs/engine.md, 'Losses', weighs it on the real and the synthetic scenes)",
    )
    patch_size: int = Field(default=8, ge=2)
    smooth_scales: int = Field(default=3, ge=1)
    distortion_weight: float = Field(
        default=0.0, ge=0,
        description="weight of mip-NeRF 360's distortion loss (the O(N) form, distances as fractions of each "
        "ray's [near, far]); 0 leaves it out",
    )
    depth_weight_final: float = Field(
        default=1.0, gt=0, le=1,
        description="lambda_depth at the end of training over lambda_depth at the start (exponential over the "
        "training limits, as lr_schedule 'budget'); 1 keeps it constant",
    )
    prior_rays: int = Field(
        default=0, ge=0,
        description="rays per step from the training cameras' centres in random directions, supervised by the "
        "prior's depth alone (voxnerf/training/prior_rays.py: space no training view sees); 0 leaves them out",
    )
    prior_ray_colour: float = Field(
        default=0.0, ge=0,
        description="weight of a colour term pulling the prior rays whose surface point no training view sees "
        "towards the training images' mean colour (a neutral guess for what no image shows); 0 leaves it out",
    )
    pixel_jitter: bool = Field(
        default=False,
        description="each training ray passes through a uniform random point of its pixel instead of its centre "
        "(instant-ngp's training rays): a pixel's colour is the mean over its footprint, and the field learns it "
        "over the footprint rather than at the one point a centre ray reads; the per-pixel depth and first hit "
        "stay the centre's (voxnerf/training/pixels.py, TrainingPixels.rays)",
    )
    error_map: float = Field(
        default=0.0, ge=0, lt=1,
        description="the share of each batch's rays drawn where the field is still wrong: the training images cut "
        "into cells of 8 x 8 pixels, each drawn in proportion to its pixels times its running squared colour error "
        "(instant-ngp's error map, voxnerf/training/error_map.py); the rest uniformly; 0 draws every ray uniformly",
    )
    error_map_weights: bool = Field(
        default=False,
        description="with error_map: weigh each ray's colour loss by its pixel's probability under uniform draws "
        "over its probability under the error map's (importance weights: the loss's expectation stays the uniform "
        "batch's); off, the rays the error map draws weigh as any",
    )
    train_background: Literal["fixed", "random"] = Field(
        default="random",
        description="the colour behind each training ray: 'random' a uniform random colour per ray and step, so a "
        "ray matches its pixel only where the field is opaque (seen surfaces cannot stay translucent and let the "
        "background tint them); 'fixed' the ``background`` (docs/benchmarks.md, 'The tuning suite')",
    )

class ScheduleConfig(_Section):
    """The optimisation: rays per step, the learning rate and its schedule, weight decay, coarse-to-fine levels."""

    rays_per_batch: int | None = Field(default=None, gt=0)
    lr: float = Field(default=1e-2, description="Adam learning rate, in (0, 1]")
    lr_decay_iters: int | None = Field(default=None, gt=0)
    lr_schedule: LrSchedule = Field(
        default="iterations",
        description="'iterations': lr x 0.1 every lr_decay_iters steps; 'budget': lr x lr_final over the run's "
        "limits (the training seconds max_seconds leaves, or max_iters), whichever ends first",
    )
    lr_final: float = Field(default=0.1, gt=0, le=1, description="lr at the end over lr at the start ('budget')")
    field_weight_decay: Annotated[float, Field(ge=0, le=1e-2)] | Literal["auto"] = Field(
        default="auto",
        description="L2 weight decay of the field's parameters (Adam's coupled form: the coefficient times each "
        "parameter joins its gradient), which keeps the hash grid's features from fitting the training images' "
        "noise; 'auto': in proportion to the variance of that noise, measured on the training images "
        "(voxnerf/training/stages/weight_decay.py); 0 leaves it out",
    )
    coarse_to_fine: float = Field(
        default=0.0, ge=0, le=1,
        description="fraction of the training limits over which the hash levels are switched on from "
        "coarse_levels to all (a smooth ramp per level); 0 trains every level from the start",
    )
    coarse_levels: int = Field(default=4, ge=1, description="hash levels active at the start of coarse_to_fine")
    weight_average: float = Field(
        default=0.995, ge=0.0, lt=1.0,
        description="renders, checkpoints and evaluations use an exponential moving average of the field's "
        "parameters with this decay per step (a lag of about 1 / (1 - decay) steps) while the optimiser steps the "
        "live ones (voxnerf/training/weight_average.py); 0 uses the last step's parameters. The default won on "
        "both halves of the tuning suite at 300 s (docs/engine.md, weight_average)",
    )

    @field_validator("lr")
    @classmethod
    def _learning_rate(cls, value: float) -> float:
        if not 0 < value <= MAX_LR:
            raise ValueError(
                f"learning rate must be in (0, {MAX_LR:g}] (VoxNeRF trains at about 1e-2), got {value!r}"
            )
        return value

class CorrectionsConfig(_Section):
    """The per-image corrections of a captured scan: appearance, pose refinement, the focal length's scale."""

    appearance: Appearance = Field(json_schema_extra=JOB,
        default="auto",
        description="'affine': a colour gain and bias per training image and channel, learnt with the field "
        "(exposure and white balance that vary between frames), held at zero mean over the images so the field "
        "keeps their average; a rendered view takes its nearest training cameras' corrections (docs/engine.md). "
        "'auto': affine for a captured scan, none for a scene whose transforms.json says it is synthetic "
        "(voxnerf/training/stages/corrections.py)",
    )
    pose_refinement: PoseRefinementMode = Field(json_schema_extra=JOB,
        default="auto",
        description="'so3xr3': a rotation and a translation per training image, learnt with the field (nerfacto's "
        "camera optimiser, voxnerf/cameras/pose_refinement.py) for scans whose poses drift (SLAM, tracking, SfM); a "
        "rendered pose takes the corrections of its nearest training cameras; the refined poses go to "
        "refined_poses.json. 'auto': so3xr3 for a captured scan, none for a synthetic scene (exact poses)",
    )
    focal_scale: Annotated[float, Field(ge=0.5, le=2.0)] | Literal["auto"] = Field(json_schema_extra=JOB,
        default="auto",
        description="the colour camera's focal lengths are the stated ones times this; 'auto': measured for a "
        "captured scan with a mesh prior (the training images' agreement through the prior at scales of the stated "
        "focal length, voxnerf/prior/focal_check.py) and used when it clearly beats the stated one, 1 for a synthetic "
        "scene; renders of the scene's own views use it, and the depth maps keep the stated camera "
        "(docs/engine.md, 'Levers of sparse-view training'; docs/benchmarks.md, 'The tuning suite')",
    )
    pose_lr: float = Field(
        default=8e-4, gt=0,
        description="learning rate of the pose corrections (on the steps that refine them, pose_every); chosen on "
        "redkitchen at 300 s among 1e-4 to 1.6e-3 (docs/engine.md, 'Levers of sparse-view training')",
    )
    pose_every: int = Field(
        default=4, ge=1,
        description="the pose corrections learn on every n-th step; the steps between move the rays as the poses "
        "stand without their gradient, which makes them as cheap as steps without pose refinement "
        "(1, 2, 4 and 8 compared on redkitchen: docs/engine.md, 'Levers of sparse-view training')",
    )
    lambda_pose: float = Field(
        default=1e-2, ge=0,
        description="weight of the pose corrections' mean translation norm (normalised units) in the loss; a tenth "
        "of it weighs their mean rotation (radians), as nerfacto's regulariser",
    )

class EvaluationConfig(_Section):
    """Evaluations during and after training, and the rays per forward pass of a render."""

    eval_chunk: int | None = Field(
        default=None, gt=0,
        description="rays per pass of the full render path (renders, evaluations); None: by the device that renders "
        "(EVAL_CHUNKS: 4,096 on a CPU, 32,768 on a GPU)",
    )
    eval_every_s: float = Field(json_schema_extra=JOB, default=60.0, ge=1e-6,
                                description="training seconds between progress evaluations (at least 1e-6: "
                                            "before every step; the due times are multiples of it)")
    eval_views: int = Field(default=4, ge=1, description="views per split in progress evaluations")
    eval_at: list[float] = Field(json_schema_extra=JOB,
        default_factory=list, description="full evaluations at these training seconds (not charged to max_seconds)"
    )
    eval_at_max_seconds: float | None = Field(json_schema_extra=WORKER,
        default=None, ge=0, description="seconds the eval_at evaluations may take in all (unbounded when None); "
        "the later ones are skipped once they are spent"
    )
    final_eval: bool = True

    def chunk_on(self, device_type: str) -> int:
        """Rays per pass of the full render path on a device of type ``device_type`` ("cpu", "cuda"): ``eval_chunk``
        when set, else :data:`EVAL_CHUNKS`' value for the device."""
        if self.eval_chunk is not None:
            return int(self.eval_chunk)
        if device_type not in EVAL_CHUNKS:
            raise ValueError(f"no evaluation chunk for device type {device_type!r}: expected one of "
                             f"{', '.join(EVAL_CHUNKS)}")
        return EVAL_CHUNKS[device_type]


SECTIONS: dict[str, type[_Section]] = {
    "run": RunConfig, "model": ModelConfig, "sampling": SamplingConfig, "loss": LossConfig,
    "schedule": ScheduleConfig, "corrections": CorrectionsConfig, "evaluation": EvaluationConfig,
}
# The settings a trained model keeps (TrainConfig.for_model), by component; None: all of it.
MODEL_SETTINGS: dict[str, tuple[str, ...] | None] = {
    "model": None,
    "sampling": None,
    "run": ("downscale", "compile", "hash_kernel"),
    "corrections": ("appearance", "pose_refinement", "focal_scale"),
    "evaluation": ("eval_chunk",),
}
# Each flat setting name -> its component.
FIELD_SECTIONS: dict[str, str] = {name: section for section, model in SECTIONS.items() for name in model.model_fields}


def field_info(name: str) -> FieldInfo:
    """The definition (type, default, limits, description) of the setting with flat name ``name``."""
    if name == "preset":
        return TrainConfig.model_fields["preset"]
    return SECTIONS[FIELD_SECTIONS[name]].model_fields[name]


def audience(name: str) -> str:
    """Who may set the setting ``name``: "job", "worker" or "internal" (see :data:`JOB`)."""
    extra = field_info(name).json_schema_extra
    return extra.get("audience", "internal") if isinstance(extra, dict) else "internal"


def settings_for(who: str) -> tuple[str, ...]:
    """The flat names of the settings :func:`audience` gives to ``who``, preset first, in component order."""
    return tuple(name for name in ("preset", *FIELD_SECTIONS) if audience(name) == who)


def nested(values: dict[str, Any]) -> dict[str, Any]:
    """``values`` with flat (``lr``) and dotted (``schedule.lr``) names put into their components; a component
    given whole (a dict or a section model) is kept, the flat and dotted names win over it. KeyError-free: an
    unknown name stays at the top level, where validation refuses it by name."""
    out: dict[str, Any] = {}
    parts: list[tuple[str, str, Any]] = []
    for key, value in values.items():
        section, _, name = key.partition(".") if "." in key else (FIELD_SECTIONS.get(key), "", key)
        if section in SECTIONS and name in SECTIONS[section].model_fields:
            parts.append((section, name, value))
        elif key in SECTIONS and isinstance(value, _Section):
            out[key] = value.model_dump(exclude_unset=True)
        else:
            out[key] = dict(value) if key in SECTIONS and isinstance(value, dict) else value
    for section, name, value in parts:
        current = out.setdefault(section, {})
        if isinstance(current, dict):
            current[name] = value
        else:  # not a mapping: left for validation to refuse
            out[f"{section}.{name}"] = value
    return out


class TrainConfig(BaseModel):
    """Everything a training run depends on, by component; stored (flat) in report.json.

    Unknown keys, NaN and infinities in any number, and a learning rate outside (0, 1] are refused with a
    pydantic ``ValidationError`` naming the field. Flat and dotted names are accepted (:func:`nested`).
    """

    model_config = STRICT

    preset: Preset = Field(default="cpu", json_schema_extra=JOB)
    run: RunConfig = Field(default_factory=RunConfig)
    model: ModelConfig = Field(default_factory=ModelConfig)
    sampling: SamplingConfig = Field(default_factory=SamplingConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    schedule: ScheduleConfig = Field(default_factory=ScheduleConfig)
    corrections: CorrectionsConfig = Field(default_factory=CorrectionsConfig)
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)

    @model_validator(mode="before")
    @classmethod
    def _flat_and_dotted_names(cls, data: Any) -> Any:
        return nested(data) if isinstance(data, dict) else data

    def resolved(self) -> TrainConfig:
        """A copy with every preset-dependent field filled in."""
        update = {}
        for section, values in PRESETS[self.preset].items():
            part = getattr(self, section)
            missing = {k: v for k, v in values.items() if getattr(part, k) is None}
            if missing:
                update[section] = part.model_copy(update=missing)
        return self.model_copy(update=update)

    def model_copy(self, *, update: dict[str, Any] | None = None, deep: bool = False) -> TrainConfig:
        """pydantic's copy; an ``update`` naming settings by their flat or dotted names (``{"lr": 0.02}``, as
        before the config was nested) goes through :meth:`updated`, so it is validated and lands in its component
        instead of becoming a stray attribute."""
        if update and any(key not in type(self).model_fields for key in update):
            return self.updated(**update)
        return super().model_copy(update=update, deep=deep)

    def updated(self, **values: Any) -> TrainConfig:
        """A validated copy with ``values`` (flat or dotted names) set."""
        return TrainConfig.model_validate(self.flat() | values)

    def for_model(self) -> dict[str, Any]:
        """What a trained model keeps of its config (its checkpoint's ``config``): the resolved field and sampling,
        and the few run settings its renders follow (:data:`MODEL_SETTINGS`): the resolution and focal length it
        trained at, the corrections it learnt, how its full render path runs. ``TrainConfig(**for_model())``
        rebuilds it, every other setting at its default."""
        resolved = self.resolved()
        out: dict[str, Any] = {}
        for section, names in MODEL_SETTINGS.items():
            part = getattr(resolved, section).model_dump()
            out[section] = part if names is None else {name: part[name] for name in names}
        return out

    def flat(self) -> dict[str, Any]:
        """Every setting by its flat name (``{"preset": ..., "lr": ..., ...}``): report.json's ``config``."""
        out: dict[str, Any] = {"preset": self.preset}
        for section in SECTIONS:
            out |= getattr(self, section).model_dump()
        return out
