"""What a user takes away from a trained synthetic room: an orbit video and an exported mesh and point cloud,
with their sizes and times and the geometry's distance to the room's true mesh.

    .venv/bin/python benchmarks/outputs_example.py RUN ROOM --out DIR [--frames 120] [--size 320x240]
        [--voxel-size 0.02] [--write-docs]

RUN: a run trained on ROOM, a scene from ``voxnerf synth`` (its ``gt_mesh.ply`` is the true geometry). Runs
``voxnerf render RUN --scene ROOM --path interpolate`` and ``voxnerf export RUN --scene ROOM --mesh/--pointcloud`` as a
user would (the CLI, one process each), then measures the exported geometry: accuracy = distance of its
vertices to the true mesh, completeness = distance of the true surface the training cameras see (their exact
depth maps) to the export.
Results go to DIR (the video, the PLYs, results.json, table.md); ``--write-docs`` puts the table into
docs/outputs.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from docs_section import publish  # noqa: E402

from voxnerf.data.scene import load_scene  # noqa: E402
from voxnerf.inference.export import distances_to_mesh  # noqa: E402
from voxnerf.prior.depth_fusion import DepthView, backproject  # noqa: E402

DOC = REPO / "docs" / "outputs.md"
SECTION = "outputs-example"


def run_cli(args: list[str]) -> float:
    """Run ``voxnerf ARGS`` in its own process; its wall time (start-up and model load included)."""
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "voxnerf", *args], check=True)
    return time.perf_counter() - started


def visible_truth(scene_dir: Path) -> np.ndarray:
    """Points [N, 3] of the true surface the training cameras see (their exact depth maps), every 4th pixel."""
    scene = load_scene(scene_dir)
    views = [DepthView(scene.depths[i], scene.intrinsics(i), scene.frames[i].c2w) for i in scene.train_indices]
    return np.concatenate([backproject(view, 4) for view in views])


def geometry_error(export: Path, truth: trimesh.Trimesh, seen: np.ndarray) -> dict:
    """Accuracy and completeness (mean and 90th percentile, scene units) of a mesh or point-cloud PLY."""
    geometry = trimesh.load(export, process=False)
    accuracy = distances_to_mesh(np.asarray(geometry.vertices), truth)
    if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces):
        completeness = distances_to_mesh(seen, geometry)
    else:  # a point cloud: distance to its nearest point
        import open3d as o3d

        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.asarray(geometry.vertices, np.float32)))
        nns = o3d.core.nns.NearestNeighborSearch(cloud.point.positions)
        nns.knn_index()
        _, d2 = nns.knn_search(o3d.core.Tensor(seen.astype(np.float32)), 1)
        completeness = np.sqrt(d2.numpy()[:, 0])
    return {
        "points": len(geometry.vertices), "faces": len(getattr(geometry, "faces", [])),
        "bytes": export.stat().st_size,
        "accuracy_mean": float(accuracy.mean()), "accuracy_p90": float(np.percentile(accuracy, 90)),
        "completeness_mean": float(completeness.mean()), "completeness_p90": float(np.percentile(completeness, 90)),
    }


def markdown(results: dict, command: str) -> str:
    video = results["video"]
    lines = [
        f"Measured {results['date']} on this 2-core CPU. Command:", "", "```", command, "```", "",
        f"Video: `voxnerf render RUN --scene ROOM --path {video['path']} --frames {video['frames']} --width "
        f"{video['width']} --height {video['height']} --out {video['path']}.mp4`: {video['frames']} frames at "
        f"{video['fps']:g} fps, "
        f"{video['width']}x{video['height']} H.264, {video['bytes'] / 1e6:.2f} MB, made in {video['seconds']:.1f} s "
        f"({video['seconds'] / video['frames'] * 1000:.0f} ms a frame, start-up and model load included).", "",
        "| export | command time | points | faces | file | accuracy mean / p90 | completeness mean / p90 |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for kind in ("mesh", "pointcloud"):
        r = results[kind]
        lines.append(
            f"| {kind} ({results['voxel_size']:g} m voxels) | {r['seconds']:.1f} s | {r['points']:,} | "
            f"{r['faces']:,} | "
            f"{r['bytes'] / 1e6:.1f} MB | {r['accuracy_mean'] * 100:.1f} / {r['accuracy_p90'] * 100:.1f} cm | "
            f"{r['completeness_mean'] * 100:.1f} / {r['completeness_p90'] * 100:.1f} cm |"
        )
    lines += ["", "Accuracy: distance of the export's vertices (points) to the room's true mesh (`gt_mesh.ply`). "
              "Completeness: distance of the true surface the training cameras see (their exact depth maps, every "
              "4th pixel) to the export; the rest of the room was never seen."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("room", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--path", choices=["interpolate", "orbit"], default="interpolate")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--voxel-size", type=float, default=0.02)
    parser.add_argument("--write-docs", action="store_true", help=f"update the results section of {DOC}")
    args = parser.parse_args()
    width, height = (int(x) for x in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    video = args.out / f"{args.path}.mp4"
    seconds = run_cli(["render", str(args.run), "--scene", str(args.room), "--path", args.path, "--frames",
                       str(args.frames), "--width", str(width), "--height", str(height), "--out", str(video)])
    frames = iio.imread(video, index=None)  # decoded through imageio-ffmpeg
    results = {"date": time.strftime("%Y-%m-%d"), "voxel_size": args.voxel_size, "video": {"path": args.path,
        "frames": int(frames.shape[0]), "width": int(frames.shape[2]), "height": int(frames.shape[1]),
        "fps": float(json.loads(Path(f"{video}.camera_path.json").read_text())["fps"]),
        "bytes": video.stat().st_size, "seconds": seconds,
    }}
    truth = trimesh.load(args.room / "gt_mesh.ply", process=False)
    seen = visible_truth(args.room)
    for kind in ("mesh", "pointcloud"):
        path = args.out / f"{kind}.ply"
        took = run_cli(["export", str(args.run), "--scene", str(args.room), f"--{kind}", str(path), "--voxel-size",
                        str(args.voxel_size)])
        results[kind] = {"seconds": took, **geometry_error(path, truth, seen)}
        print(kind, json.dumps(results[kind]), flush=True)
    command = ".venv/bin/python benchmarks/outputs_example.py " + " ".join(sys.argv[1:])
    publish(args.out, results, markdown(results, command), DOC, SECTION, args.write_docs)


if __name__ == "__main__":
    main()
