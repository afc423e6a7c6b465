"""The CLI and the REST service render the same pose to the same pixels.

A short job trains through the running service (HTTP only); ``voxnerf render`` then renders the job's run
directory, and ``POST /render`` the job, for the same pose and size. Every output is decoded from both and
compared: PNG rgb (8-bit colour), depth (16-bit) and opacity (8-bit gray), and the EXR channels.
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from service_fixtures import first_pose, start_service, upload_scene, wait_until_succeeded

from voxnerf.cli import main
from voxnerf.data.image_io import decode_exr

pytestmark = pytest.mark.slow

JOB = {"max_iters": 3, "compile": False, "seed": 2}
TRAIN_TIMEOUT_S = 600
WIDTH, HEIGHT = 32, 24


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("parity") / "service")
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def client(service):
    with service.client(timeout_s=120) as c:
        yield c


@pytest.fixture(scope="module")
def job(service, client, small_room) -> dict:
    scene = upload_scene(client, small_room)
    response = client.post(f"/scenes/{scene['id']}/jobs", json=JOB)
    assert response.status_code == 202, response.text
    return wait_until_succeeded(service, client, response.json()["id"], TRAIN_TIMEOUT_S)


@pytest.fixture(scope="module")
def run_dir(service, job) -> Path:
    """The job's run directory: the one checkpoint under the service's data directory that names the job."""
    found = [p.parent for p in service.data_dir.rglob("checkpoint.pt") if job["id"] in p.parent.as_posix()]
    assert len(found) == 1, f"expected one checkpoint for job {job['id']}, found {found}"
    return found[0]


@pytest.fixture(scope="module")
def pose_file(small_room, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("pose") / "pose.json"
    path.write_text(json.dumps({"transform_matrix": first_pose(small_room), "w": WIDTH, "h": HEIGHT}))
    return path


def _post(client, job: dict, pose_file: Path, fmt: str, outputs: list[str]) -> bytes:
    pose = json.loads(pose_file.read_text())["transform_matrix"]
    body = {"job_id": job["id"], "transform_matrix": pose, "width": WIDTH, "height": HEIGHT, "format": fmt,
            "outputs": outputs}
    response = client.post("/render", json=body)
    assert response.status_code == 200, response.text
    return response.content


def _cli(run_dir: Path, pose_file: Path, out: Path) -> None:
    code = main(["render", str(run_dir), "--pose", str(pose_file), "--out", str(out), "--depth", "--opacity",
                 "--device", "cpu"])
    assert code == 0


def test_png_outputs_agree(client, job, run_dir, pose_file, tmp_path):
    _cli(run_dir, pose_file, tmp_path / "view.png")
    cases = (("rgb", "view.png", np.uint8, (HEIGHT, WIDTH, 3)),
             ("depth", "view_depth.png", np.uint16, (HEIGHT, WIDTH)),
             ("opacity", "view_opacity.png", np.uint8, (HEIGHT, WIDTH)))
    for name, file, dtype, shape in cases:
        from_cli = iio.imread(tmp_path / file)
        from_api = iio.imread(_post(client, job, pose_file, "png", [name]))
        assert from_cli.dtype == from_api.dtype == dtype, name
        assert from_cli.shape == from_api.shape == shape, name
        # the same model on the same CPU: at most one unit of rounding apart
        assert np.abs(from_cli.astype(np.int64) - from_api.astype(np.int64)).max() <= 1, name
    assert iio.imread(tmp_path / "view_depth.png").max() > 0, "the depth is not all empty"


def test_exr_outputs_agree(client, job, run_dir, pose_file, tmp_path):
    _cli(run_dir, pose_file, tmp_path / "view.exr")
    from_cli = decode_exr((tmp_path / "view.exr").read_bytes())
    from_api = decode_exr(_post(client, job, pose_file, "exr", ["rgb", "depth", "opacity"]))
    assert sorted(from_cli) == sorted(from_api) == ["A", "B", "G", "R", "Z"]
    for name in from_cli:
        assert from_cli[name].shape == from_api[name].shape == (HEIGHT, WIDTH), name
        np.testing.assert_allclose(from_cli[name], from_api[name], rtol=1e-4, atol=1e-4, err_msg=name)
