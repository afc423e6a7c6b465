"""First-hit throughput on the redkitchen prior (sigma 0.02 m, scene units): random pixels of random frames.

Usage: python bench_octree.py DEVICE THREADS N1,N2,...   e.g. python bench_octree.py cpu 2 307200,1000000
"""
import json
import sys
import time
from pathlib import Path

import torch

from voxnerf.cameras.rays import camera_rays
from voxnerf.prior.loading import load_prior
from voxnerf.prior.octree import SparseVoxelOctree

device, threads, sizes = sys.argv[1], int(sys.argv[2]), [int(x) for x in sys.argv[3].split(",")]
torch.set_num_threads(threads)
scene = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen"
meta = json.loads((scene / "transforms.json").read_text())
prior = load_prior(scene / meta["prior_file_path"], meta["prior_sigma"])
svo = SparseVoxelOctree.from_points(torch.from_numpy(prior.points).float(), prior.sigma).to(device)
print(device, "threads", torch.get_num_threads(), "nodes per level", svo.summary()["nodes_per_level"])
c2w = torch.tensor([f["transform_matrix"] for f in meta["frames"]], dtype=torch.float32)
g = torch.Generator().manual_seed(0)
for n in sizes:
    frame = torch.randint(0, len(c2w), (n,), generator=g)
    px, py = torch.randint(0, meta["w"], (n,), generator=g), torch.randint(0, meta["h"], (n,), generator=g)
    o, d, _ = camera_rays(c2w[frame], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], px, py)
    o, d = o.to(device), d.to(device)
    svo.first_hit(o[:5000], d[:5000], 0.0, 100.0)  # warm-up
    best = float("inf")
    for _ in range(3):
        if device != "cpu":
            torch.cuda.synchronize()
        start = time.perf_counter()
        t, hit = svo.first_hit(o, d, 0.0, 100.0)
        if device != "cpu":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    print(f"{n} rays: {best:.3f} s, {n / best / 1e6:.2f} M rays/s, hit fraction {hit.float().mean():.3f}")
