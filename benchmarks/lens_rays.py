"""Training rays of distorted cameras: the per-camera direction table against the lens's inverse model per batch.

40 frames of one OPENCV camera at 160 x 120; 4096 random training pixels; the three ways interleaved six times,
50 calls each, and the median time per call printed (ratios are what to read: the machine is shared).

    .venv/bin/python benchmarks/lens_rays.py
"""

from __future__ import annotations

import time

import torch

from voxnerf.cameras.lens import LensBatch
from voxnerf.cameras.rules import Lens
from voxnerf.training.pixels import TrainingPixels, direction_table


def main() -> int:
    torch.set_num_threads(2)
    n, h, w = 40, 120, 160
    intr = torch.tensor([[120.0, 120.0, 80.0, 60.0]] * n)
    lens = LensBatch.of([Lens("OPENCV", k1=-0.15, k2=0.02, p1=0.001, p2=-0.001)] * n)
    poses = torch.eye(4).repeat(n, 1, 1)
    images = torch.zeros(n, h, w, 3, dtype=torch.uint8)
    ways = {
        "direction table": TrainingPixels(images, poses, intr, lens, directions=direction_table(intr, lens, h, w)),
        "inverse model per batch": TrainingPixels(images, poses, intr, lens),
        "pinhole (no lens)": TrainingPixels(images, poses, intr, None),
    }
    g = torch.Generator().manual_seed(0)
    pixels = (torch.randint(0, n, (4096,), generator=g), torch.randint(0, h, (4096,), generator=g),
              torch.randint(0, w, (4096,), generator=g))
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(6):
        for name, way in ways.items():
            started = time.perf_counter()
            for _ in range(50):
                way.rays(*pixels)
            times[name].append((time.perf_counter() - started) / 50 * 1e3)
    for name, values in times.items():
        print(f"{name}: median {sorted(values)[len(values) // 2]:.2f} ms per 4096 rays")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
