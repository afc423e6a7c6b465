"""``voxnerf import images``: a folder of photos without poses, posed by structure from motion (pycolmap), as a scene.

Structure from motion runs inside the product with pycolmap's bundled COLMAP (CPU SIFT, no GPU needed):

- Photos: the JPEG and PNG files at the top of the folder, in name order (a phone names them in capture
  order). Each is decoded once; one that does not decode is skipped and named. A photo whose EXIF orientation
  is not "upright" is written upright first (JPEG quality JPEG_QUALITY), so that COLMAP and the engine see the
  same pixels; the others are used byte for byte.
- Cameras: one shared camera when every photo has the same size and the same EXIF make, model and focal length;
  else one camera per photo. The model is COLMAP's SIMPLE_RADIAL (one focal length, principal point, radial k1),
  written as the engine's ``OPENCV`` lens model with k1 (:mod:`voxnerf.data.importers.colmap`): rays are
  distorted in the engine, the photos are never resampled. (COLMAP's OPENCV model, with separate x and y focal
  lengths and tangential terms, let the synthetic room's path converge to a focal ratio of 18 in this project's
  tests; square pixels hold for phone and robot cameras.) COLMAP takes the starting focal length from EXIF when
  it has one, else 1.2 times the longer side.
- Matching: exhaustive (every pair) up to EXHAUSTIVE_MAX_IMAGES photos, else sequential with COLMAP's quadratic
  overlap (each photo with the ones 1, 2, 4, 8, ... places after it in name order, up to 2**(SEQUENTIAL_OVERLAP
  - 1): about n log2(n) pairs): ``matching`` overrides. A video's frames are always matched sequentially.
- Mapping: COLMAP's incremental mapper (one thread, seed 0; its start and registration thresholds lowered:
  :data:`INIT_MIN_TRIANGULATION_DEG`); the largest reconstruction is kept (ties: the one with more points).
  Feature extraction and matching use every core, so the registered set can vary slightly run to run.
  Fewer than MIN_REGISTERED registered photos is an error; each photo left out is named with its reason
  (:data:`REASONS`).
- The kept reconstruction is written as a scene by the COLMAP importer's own path
  (:func:`voxnerf.data.importers.colmap.import_reconstruction`): poses, intrinsics, the sparse points as the
  prior with ``prior_sigma`` from their reprojection errors. COLMAP's world frame and scale are arbitrary (a
  similarity away from metric); the scene keeps them.

The work (staged photos, COLMAP's database) happens in a temporary folder beside the output, removed at the end;
the scene itself is written by :func:`voxnerf.data.importers.writer.build_scene` (nothing left at ``out`` on
error).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from voxnerf.data.importers import writer
from voxnerf.data.importers.colmap import import_reconstruction
from voxnerf.data.importers.monitor import CountWatch, ImportCancelled, ImportMonitor
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.errors import SceneError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
MATCHING_CHOICES = ("auto", "exhaustive", "sequential")
EXHAUSTIVE_MAX_IMAGES = 60
"""Up to this many photos every pair is matched (n(n-1)/2 pairs: 1770 at 60); beyond, sequential matching."""
EXHAUSTIVE_BLOCK = 10
"""Exhaustive matching goes through the images in blocks of this many (COLMAP's default is 50): a cancel is seen
between two blocks."""
EXTRACT_CHUNK = 8
"""Photos whose features one extraction call finds: the import's progress is reported between two calls (nothing
reads the database while pycolmap writes it, :class:`~voxnerf.data.importers.monitor.CountWatch`)."""
SEQUENTIAL_OVERLAP = 15
"""Sequential matching with COLMAP's quadratic overlap: each image is matched with the ones 2**k places after it,
k < SEQUENTIAL_OVERLAP (COLMAP 4 pairs only these, not also the SEQUENTIAL_OVERLAP next ones)."""
MIN_REGISTERED = 3
"""Fewest registered photos a scene is made of; also the smallest reconstruction COLMAP keeps."""
MAX_FEATURES = 4096
"""SIFT features per photo: enough for indoor scenes, and it keeps matching on a CPU to minutes."""
MAX_FEATURE_IMAGE_SIZE = 1600
"""Longest side (pixels) features are extracted at; larger photos are scaled for extraction only (COLMAP scales
the keypoints back), the scene keeps them at full size."""
INIT_MIN_TRIANGULATION_DEG = 4.0
INIT_MIN_INLIERS = 50
REGISTER_MIN_INLIERS = 15
"""The incremental mapper's thresholds for its first pair (triangulation angle, inlier matches) and for
registering a further image (2D-3D inliers), below COLMAP's defaults (16 degrees, 100, 30), which suit
thousands of features per image: on 25-50 frames of a slow indoor video at 320 x 240 (~500 features each) the
defaults left a third to half of the frames in side reconstructions on some seeds, these registered all of them
on every seed tried. Poses are bundle-adjusted all the same."""
SFM_SEED = 0
"""The seed of structure from motion's random choices before mapping: COLMAP's global generator and each image
pair's RANSAC in geometric verification (COLMAP seeds those at random by default, and its matcher threads verify
pairs in any order). With one extraction thread and the mapper's own seeds (MAPPING_SEEDS; it runs
single-threaded) the same photos give the same poses on one machine."""
MAPPING_SEEDS = (0, 1, 2)
"""The incremental mapper's seeds, tried in turn until one registers every photo into one reconstruction; the
attempt whose largest reconstruction registers most is kept (then the most points). On one seed 20 redkitchen
photos split 13 + 7, on the next five seeds all 20 registered: where the mapper starts and which image it
registers next are random choices, and a split is often only an unlucky one."""
JPEG_QUALITY = 95
CAMERA_MODEL = "SIMPLE_RADIAL"
REASONS = {
    "undecodable": "cannot be decoded as a JPEG or PNG image",
    "no_features": "no features found (blank, blurred or very small)",
    "no_match": "no verified match with any other image (it does not overlap them)",
    "other_model": "overlaps only images outside the largest reconstruction (a separate group)",
    "not_registered": "matched images of the reconstruction but could not be registered (too few matches to "
    "its 3D points)",
}
"""Why a photo is not in the scene, as the summary says it."""
_EXIF_ORIENTATION, _EXIF_MAKE, _EXIF_MODEL, _EXIF_IFD, _EXIF_FOCAL = 0x0112, 0x010F, 0x0110, 0x8769, 0x920A


@dataclass
class StagedPhotos:
    """Photos ready for COLMAP in one flat folder, and those left out before SfM (name -> reason key)."""

    dir: Path
    names: list[str] = field(default_factory=list)
    left_out: dict[str, str] = field(default_factory=dict)
    camera_keys: set = field(default_factory=set)
    reoriented: int = 0


@dataclass
class SfmResult:
    """The kept reconstruction and what happened to every photo."""

    recon: object
    matching: str
    camera_mode: str
    model_sizes: list[int]
    unregistered: dict[str, str]
    mapping_attempts: list[tuple[int, int]]  # (seed, photos its largest reconstruction registered) of each attempt


def list_photos(src: Path) -> list[Path]:
    """The JPEG / PNG files at the top of ``src`` in name order; SceneError when there are none."""
    if not src.is_dir():
        raise SceneError(src, "not a directory")
    photos = sorted(p for p in src.iterdir()
                    if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not photos:
        raise SceneError(src, f"no photos: no {', '.join(IMAGE_SUFFIXES)} files in the folder")
    return photos


def stage_photo(src: Path, staged: StagedPhotos) -> None:
    """Decode ``src`` once; copy it (or write it upright when EXIF rotates it) into ``staged.dir``."""
    from PIL import Image, ImageOps

    try:
        with Image.open(src) as im:
            im.load()
            if im.format not in ("JPEG", "PNG") or im.mode not in ("L", "RGB", "RGBA", "LA", "P"):
                staged.left_out[src.name] = "undecodable"
                return
            exif = im.getexif()
            orientation = exif.get(_EXIF_ORIENTATION, 1)
            if orientation not in (1, None):
                upright = ImageOps.exif_transpose(im).convert("RGB")
                upright.save(staged.dir / src.name, format=im.format, quality=JPEG_QUALITY)
                staged.reoriented += 1
                size = upright.size
            else:
                shutil.copyfile(src, staged.dir / src.name)
                size = im.size
            focal = exif.get_ifd(_EXIF_IFD).get(_EXIF_FOCAL)
            staged.camera_keys.add((size, exif.get(_EXIF_MAKE), exif.get(_EXIF_MODEL),
                                    float(focal) if focal is not None else None))
    except (OSError, ValueError, Image.DecompressionBombError):  # unreadable, truncated or not an image
        staged.left_out[src.name] = "undecodable"
        return
    staged.names.append(src.name)


def stage_photos(photos: list[Path], work: Path) -> StagedPhotos:
    staged = StagedPhotos(work / "images")
    staged.dir.mkdir(parents=True)
    for photo in photos:
        stage_photo(photo, staged)
    return staged


@contextmanager
def work_dir(out: Path) -> Iterator[Path]:
    """A temporary folder beside ``out`` for SfM's files, removed however the block ends."""
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.sfm-", dir=out.parent))
    try:
        yield work
    finally:
        shutil.rmtree(work, ignore_errors=True)


@contextmanager
def _quiet_colmap() -> Iterator[None]:
    """COLMAP's progress log (one line per image and pair) silenced; errors still print."""
    import pycolmap

    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def resolve_matching(matching: str, n_images: int) -> str:
    if matching not in MATCHING_CHOICES:
        raise ValueError(f"matching must be one of {', '.join(MATCHING_CHOICES)}, not {matching!r}")
    if matching != "auto":
        return matching
    return "exhaustive" if n_images <= EXHAUSTIVE_MAX_IMAGES else "sequential"


SFM_SPANS = {"extracting": (0.0, 0.3), "matching": (0.3, 0.6), "mapping": (0.6, 0.95)}
"""The share of structure from motion's work each of its phases takes, as its progress reports it (roughly what
they took on redkitchen's 100 photos; writing the scene takes the rest)."""


def sequential_pairs(n_images: int, overlap: int = SEQUENTIAL_OVERLAP, quadratic: bool = True) -> int:
    """Image pairs COLMAP's sequential matching compares among ``n_images`` in name order: each image with the
    ones ``2**k`` places after it (``k < overlap``) when ``quadratic``, else with its ``overlap`` next ones."""
    gaps = {2**k for k in range(overlap)} if quadratic else set(range(1, overlap + 1))
    return sum(max(n_images - gap, 0) for gap in gaps)


@contextmanager
def _cancellable(token) -> Iterator[None]:
    """A pycolmap call that ``token`` may cancel: its InterruptedError, or a cancel it saw too late to act on,
    becomes ImportCancelled."""
    try:
        yield
    except InterruptedError:
        raise ImportCancelled("the import was cancelled") from None
    if token.is_cancelled:
        raise ImportCancelled("the import was cancelled")


def run_sfm(staged: StagedPhotos, work: Path, matching: str, named: Path,
            monitor: ImportMonitor | None = None) -> SfmResult:
    """Features, matches and incremental mapping of the staged photos; the largest reconstruction.

    ``named``: the folder or file errors name. ``monitor``: each phase's progress (images with features, image
    pairs matched, images registered) and a stop request, which cancels pycolmap's running call
    (ImportCancelled). Raises SceneError when no reconstruction has MIN_REGISTERED photos.
    """
    import pycolmap

    if len(staged.names) < MIN_REGISTERED:
        raise SceneError(named, f"{len(staged.names)} decodable photos; structure from motion needs at least "
                         f"{MIN_REGISTERED} that overlap")
    shared = len(staged.camera_keys) == 1
    matching = resolve_matching(matching, len(staged.names))
    database = work / "database.db"
    monitor = monitor or ImportMonitor()
    token = pycolmap.CancellationToken()
    pycolmap.set_random_seed(SFM_SEED)
    with _quiet_colmap():
        monitor.check()
        _extract(staged, database, shared, monitor.within(*SFM_SPANS["extracting"]), token)
        _match(database, len(staged.names), matching, monitor.within(*SFM_SPANS["matching"]), token)
        models, attempts = _map_best(staged, database, work / "sparse", monitor.within(*SFM_SPANS["mapping"]), token)
    models = sorted(models.values(), key=_model_rank, reverse=True)
    sizes = [r.num_reg_images() for r in models]
    if not models or sizes[0] < MIN_REGISTERED:
        raise SceneError(named, f"structure from motion registered {sizes[0] if sizes else 0} of "
                         f"{len(staged.names)} photos (at least {MIN_REGISTERED} needed): "
                         f"{_why_none(database, len(staged.names))}")
    unregistered = _unregistered(database, models, _mapper_options(SFM_SEED).min_num_matches)
    camera_mode = "one shared camera" if shared else "one camera per image"
    return SfmResult(models[0], matching, camera_mode, sizes, unregistered, attempts)


@contextmanager
def _open_database(database: Path) -> Iterator:
    """A pycolmap connection to ``database``, closed on the way out (only between pycolmap's calls:
    :class:`CountWatch`)."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        yield db
    finally:
        db.close()


def _database_count(database: Path, method: str) -> Callable[[], int | None]:
    """``pycolmap.Database.<method>()`` of ``database``, once the call writing it returned (:class:`CountWatch`:
    never while it runs); None when it cannot be opened."""

    def count() -> int | None:
        if not database.is_file():
            return None
        try:
            with _open_database(database) as db:
                return int(getattr(db, method)())
        except Exception:  # not created: the call wrote nothing
            return None

    return count


def _extract(staged: StagedPhotos, database: Path, shared: bool, monitor: ImportMonitor, token) -> None:
    """SIFT features of every staged photo into ``database`` (one camera, or one per photo when not ``shared``);
    progress in images read."""
    import pycolmap

    mode = pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE
    reader = pycolmap.ImageReaderOptions(camera_model=CAMERA_MODEL)
    # one extraction thread: with several, the photos enter the database (and get their image ids) in the order
    # their threads finish, and the mapper's choices follow the ids
    extraction = pycolmap.FeatureExtractionOptions(max_image_size=MAX_FEATURE_IMAGE_SIZE, num_threads=1)
    extraction.sift.max_num_features = MAX_FEATURES
    n = len(staged.names)
    for start in range(0, n, EXTRACT_CHUNK):
        with _cancellable(token), CountWatch(monitor, _database_count(database, "num_images"), n,
                                             "extracting features", "images", token, before=start):
            pycolmap.extract_features(database, staged.dir, image_names=staged.names[start:start + EXTRACT_CHUNK],
                                      camera_mode=mode, reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu, cancellation_token=token)
        if shared and reader.existing_camera_id < 0:  # the later calls' photos share the first call's camera
            reader.existing_camera_id = _shared_camera_id(database)


def _shared_camera_id(database: Path) -> int:
    """The id of the camera the photos in ``database`` share; -1 while it holds none (no photo of the first call
    was read: the next call makes the camera)."""
    with _open_database(database) as db:
        cameras = db.read_all_cameras()
    return cameras[0].camera_id if cameras else -1


def _match(database: Path, n_images: int, matching: str, monitor: ImportMonitor, token) -> None:
    """Matches of the image pairs ``matching`` picks, geometrically verified; progress in pairs matched."""
    import pycolmap

    pairs = n_images * (n_images - 1) // 2 if matching == "exhaustive" else sequential_pairs(n_images)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = SFM_SEED  # COLMAP's default (-1) seeds each pair's RANSAC at random
    with _cancellable(token), CountWatch(monitor, _database_count(database, "num_matched_image_pairs"), pairs,
                                         f"matching features ({matching})", "image pairs", token):
        if matching == "exhaustive":
            pairing = pycolmap.ExhaustivePairingOptions(block_size=EXHAUSTIVE_BLOCK)
            pycolmap.match_exhaustive(database, pairing_options=pairing, verification_options=verification,
                                      device=pycolmap.Device.cpu, cancellation_token=token)
        else:
            pairing = pycolmap.SequentialPairingOptions(overlap=SEQUENTIAL_OVERLAP, quadratic_overlap=True)
            pycolmap.match_sequential(database, pairing_options=pairing, verification_options=verification,
                                      device=pycolmap.Device.cpu, cancellation_token=token)


def _model_rank(model) -> tuple[int, int]:
    """How reconstructions compare: photos registered, then points."""
    return model.num_reg_images(), model.num_points3D()


def _map_best(staged: StagedPhotos, database: Path, sparse: Path, monitor: ImportMonitor,
              token) -> tuple[dict, list[tuple[int, int]]]:
    """:func:`_map` under each of MAPPING_SEEDS in turn until one registers every photo into one reconstruction:
    the reconstructions of the attempt whose largest ranks first (:func:`_model_rank`), and ``(seed, photos its
    largest registered)`` of every attempt. The attempts share the mapping's span of progress, which never goes
    back."""
    import pycolmap

    n = len(staged.names)
    best: dict = {}
    attempts: list[tuple[int, int]] = []
    floor = [0.0]  # the furthest fraction reported so far
    for attempt, seed in enumerate(MAPPING_SEEDS):
        pycolmap.set_random_seed(seed)
        out = sparse / str(seed)
        out.mkdir(parents=True)
        label = "" if attempt == 0 else f" (attempt {attempt + 1} of {len(MAPPING_SEEDS)}, seed {seed})"
        models = _map(staged, database, out, _mapper_options(seed), monitor, token, label, floor)
        largest = max(models.values(), key=_model_rank, default=None)
        attempts.append((seed, largest.num_reg_images() if largest is not None else 0))
        if largest is not None and (not best or _model_rank(largest) > max(map(_model_rank, best.values()))):
            best = models
        if attempts[-1][1] == n:
            break
    return best, attempts


def _map(staged: StagedPhotos, database: Path, sparse: Path, options, monitor: ImportMonitor, token,
         label: str = "", floor: list[float] | None = None) -> dict:
    """COLMAP's incremental mapping; its reconstructions. Progress in images registered (COLMAP calls back after
    its first pair and after each image it adds; a second reconstruction's images count on, up to the total),
    each step's text followed by ``label``, its fraction never below ``floor[0]`` (which it raises), and a stop
    request cancels it between two images."""
    import pycolmap

    n = len(staged.names)
    registered = 0
    floor = floor if floor is not None else [0.0]

    def report(fraction: float) -> None:
        floor[0] = max(floor[0], fraction)
        monitor.step(f"registering images: {registered} of {n}{label}", floor[0])

    def registered_more(count: int) -> None:
        nonlocal registered
        registered = min(registered + count, n)
        report(registered / n)
        if monitor.should_stop():
            token.cancel()

    report(0.0)
    with _cancellable(token):
        return pycolmap.incremental_mapping(database, staged.dir, sparse, options,
                                            initial_image_pair_callback=lambda: registered_more(2),
                                            next_image_callback=lambda: registered_more(1), cancellation_token=token)


def _mapper_options(seed: int):
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions(min_model_size=MIN_REGISTERED, random_seed=seed, num_threads=1)
    options.mapper.init_min_tri_angle = INIT_MIN_TRIANGULATION_DEG
    options.mapper.init_min_num_inliers = INIT_MIN_INLIERS
    options.mapper.abs_pose_min_num_inliers = REGISTER_MIN_INLIERS
    return options


def _match_graph(database: Path, min_matches: int) -> tuple[dict[int, str], dict[int, int], dict[int, set[int]]]:
    """Image id -> name, image id -> keypoint count, image id -> the ids it has a verified match with."""
    import pycolmap

    with _open_database(database) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        keypoints = {image_id: db.num_keypoints_for_image(image_id) for image_id in names}
        pair_ids, geometries = db.read_two_view_geometries()
        partners: dict[int, set[int]] = {image_id: set() for image_id in names}
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            if len(geometry.inlier_matches) >= min_matches:
                first, second = pycolmap.pair_id_to_image_pair(pair_id)
                partners[first].add(second)
                partners[second].add(first)
    return names, keypoints, partners


def _why_none(database: Path, n_photos: int) -> str:
    names, keypoints, partners = _match_graph(database, 15)
    if not any(keypoints.values()):
        return "no features were found in any photo"
    matched = sum(1 for ids in partners.values() if ids)
    if matched < n_photos:
        return (f"{matched} of {n_photos} photos have a verified match with another; the photos must overlap "
                "(each part of the scene seen from several places)")
    return ("every photo matches another, but the viewpoints differ too little to triangulate from (move the "
            "camera between photos, do not only turn it)")


def _unregistered(database: Path, models: list, min_matches: int) -> dict[str, str]:
    """Name -> reason key for the photos the kept (first) reconstruction lacks."""
    names, keypoints, partners = _match_graph(database, min_matches)
    kept = set(models[0].reg_image_ids())
    reasons = {}
    for image_id, name in sorted(names.items(), key=lambda item: item[1]):
        if image_id in kept:
            continue
        if keypoints.get(image_id, 0) == 0:
            reasons[name] = "no_features"
        elif not partners[image_id]:
            reasons[name] = "no_match"
        elif not partners[image_id] & kept:
            reasons[name] = "other_model"
        else:
            reasons[name] = "not_registered"
    return reasons


def reconstruct_and_write(
    staged: StagedPhotos,
    work: Path,
    out: Path,
    splits: PaperSplitRule | None,
    matching: str,
    fmt: str,
    named: Path,
    describe_name: Callable[[str], str] = str,
    monitor: ImportMonitor | None = None,
) -> dict:
    """SfM on the staged photos and the kept reconstruction written as the scene ``out``; the summary.

    ``describe_name`` turns a staged file name into what the summary calls it (a video names the frame's time);
    ``monitor`` follows the work and may stop it (:func:`run_sfm`).
    """
    monitor = monitor or ImportMonitor()
    result = run_sfm(staged, work, matching, named, monitor)
    monitor.step("writing the scene", SFM_SPANS["mapping"][1])
    monitor.check()
    summary = import_reconstruction(result.recon, staged.dir, out, splits, fmt, named)
    left_out = {**{name: REASONS[key] for name, key in staged.left_out.items()},
                **{name: REASONS[key] for name, key in result.unregistered.items()}}
    skipped = dict(summary["skipped"])
    for reason in left_out.values():
        skipped[reason] = skipped.get(reason, 0) + 1
    total = len(staged.names) + len(staged.left_out)
    registered = result.recon.num_reg_images()
    sfm = {
        "images": total,
        "registered": registered,
        "not_registered": {describe_name(name): reason for name, reason in sorted(left_out.items())},
        "matching": result.matching,
        "cameras": result.camera_mode,
        "reconstructions": result.model_sizes,
        "mapping_attempts": [{"seed": seed, "registered": count} for seed, count in result.mapping_attempts],
        "mean_reprojection_error_px": float(result.recon.compute_mean_reprojection_error()),
        "points": int(result.recon.num_points3D()),
    }
    notes = [f"structure from motion registered {registered} of {total} images ({result.camera_mode}, "
             f"{result.matching} matching, mean reprojection error {sfm['mean_reprojection_error_px']:.2f} px); "
             "poses and scale are COLMAP's (a similarity away from metric)"]
    if len(result.mapping_attempts) > 1:
        tried = ", ".join(f"seed {seed}: {count}" for seed, count in result.mapping_attempts)
        notes.append(f"the mapper's first seed left photos out, so it ran under {len(result.mapping_attempts)} "
                     f"seeds (registered {tried} of {len(staged.names)}): the best kept")
    if "other_model" in result.unregistered.values():
        notes.append(f"the photos form {len(result.model_sizes)} reconstructions of "
                     f"{', '.join(map(str, result.model_sizes))} images (they may share images): the largest kept")
    if staged.reoriented:
        notes.append(f"{staged.reoriented} photos written upright from their EXIF orientation (JPEG quality "
                     f"{JPEG_QUALITY})")
    notes += [f"not registered: {name}: {reason}" for name, reason in list(sfm["not_registered"].items())[:20]]
    if len(left_out) > 20:
        notes.append(f"... and {len(left_out) - 20} more not registered (the summary's sfm entry lists all)")
    return {**summary, "skipped": skipped, "sfm": sfm, "notes": summary["notes"] + notes}


def import_images(
    src: str | Path, out: str | Path, splits: PaperSplitRule | None = None, matching: str = "auto",
    monitor: ImportMonitor | None = None,
) -> dict:
    """Pose the photos in ``src`` by structure from motion and write them as a scene at ``out`` (absent or empty).

    ``matching``: ``auto`` (exhaustive up to EXHAUSTIVE_MAX_IMAGES photos, else sequential), ``exhaustive`` or
    ``sequential``. Returns the importer summary with an ``sfm`` entry (images, registered, the photos not
    registered and why, matching, cameras, reconstruction sizes, mean reprojection error). Raises SceneError
    naming the folder or file at fault, ImportCancelled when ``monitor`` asks it to stop; nothing is left at
    ``out`` on error.
    """
    src, out = Path(src), Path(out)
    writer.check_out_dir(out)
    resolve_matching(matching, 0)
    photos = list_photos(src)
    with work_dir(out) as work:
        staged = stage_photos(photos, work)
        return reconstruct_and_write(staged, work, out, splits, matching, "images", src, monitor=monitor)
