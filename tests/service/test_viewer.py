"""The viewer (issue #21, items 2-4): its endpoints on an in-process app (a job's scene cameras, the prior's
sample, a camera's ground-truth image, paths through keyframes, each refusal), and the page itself in a real
headless browser (playwright driving Debian's /usr/bin/chromium) on a trained job, opened from its dashboard
row: a drag renders a new pose, a snapped evaluation camera shows the same pixels as ``POST /render`` of that
pose, depth shows with a colour bar, and two keyframes become a video job. Screenshots are saved under the
browser test's temporary directory."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from browser_fixtures import browser_page, csp_reports
from fastapi.testclient import TestClient
from PIL import Image
from service_fixtures import start_service, wait_for, zip_scene

from app.core import jobstore
from app.core.settings import Settings
from app.main import create_app
from voxnerf.cameras.paths import parse_nerfstudio
from voxnerf.synthetic import RoomSpec, make_room_scene

TOKEN = "viewer-token"


@pytest.fixture(scope="module")
def tiny_rooms(tmp_path_factory) -> dict[str, Path]:
    """Two 24x18 rooms of 7 frames (4 train, 3 test): one with a point prior and depth maps, one with neither."""
    root = tmp_path_factory.mktemp("viewer-rooms")
    spec = dict(width=24, height=18, n_frames=16, train_every=4, n_gaps=0, gap_len=0, prior_max_points=20_000)
    return {
        "prior": make_room_scene(root / "prior", RoomSpec(**spec)),
        "bare": make_room_scene(root / "bare", RoomSpec(**spec, prior_kind="none", write_depth=False)),
    }


@pytest.fixture
def api(tmp_path, tiny_rooms):
    """An in-process app with one job on each tiny room (queued: the viewer's endpoints need no worker)."""
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", device="cpu", api_token=TOKEN,
                        sweep_interval_s=3600)
    with TestClient(create_app(settings), headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        jobs = {}
        for name, room in tiny_rooms.items():
            scene_id = jobstore.new_id()
            shutil.copytree(room, settings.scenes_dir / scene_id)
            jobstore.add_scene(settings, scene_id, name, {"frames": 7}, 1)
            jobs[name] = jobstore.create_job(settings, scene_id, {"max_iters": 1}).id
        yield client, settings, jobs


def _transforms(room: Path) -> dict:
    return json.loads((room / "transforms.json").read_text())


# ------------------------------------------------------------------------------------------------ endpoints


def test_cameras_are_the_scenes_frames_in_scene_units_with_their_splits(api, tiny_rooms):
    client, _settings, jobs = api
    body = client.get(f"/jobs/{jobs['prior']}/cameras").json()
    meta = _transforms(tiny_rooms["prior"])
    assert [f["name"] for f in body["frames"]] == [f["file_path"] for f in meta["frames"]]
    for frame, raw in zip(body["frames"], meta["frames"], strict=True):
        np.testing.assert_allclose(frame["transform_matrix"], raw["transform_matrix"], atol=1e-9)
        assert (frame["width"], frame["height"]) == (24, 18)
    test_names = set(meta["test_filenames"])
    assert {f["name"] for f in body["frames"] if "test" in f["splits"]} == test_names
    assert body["units"] == "metres" and body["depth_unit_scale"] == pytest.approx(0.001)


def test_a_scene_without_depth_maps_is_in_scene_units(api):
    client, _settings, jobs = api
    assert client.get(f"/jobs/{jobs['bare']}/cameras").json()["units"] == "scene units"


def test_the_prior_preview_is_a_bounded_sample_of_the_prior(api):
    client, _settings, jobs = api
    body = client.get(f"/jobs/{jobs['prior']}/prior-preview").json()
    points = np.asarray(body["points"]).reshape(-1, 3)
    assert body["total"] > 4000 and len(points) == 4000 and np.isfinite(points).all()
    assert body["colors"] is None or len(body["colors"]) == len(body["points"])


def test_a_scene_without_a_prior_has_no_preview(api):
    client, _settings, jobs = api
    response = client.get(f"/jobs/{jobs['bare']}/prior-preview")
    assert response.status_code == 404 and "no prior" in response.json()["detail"]


def test_a_cameras_image_is_its_frames_file(api, tiny_rooms):
    client, _settings, jobs = api
    frame = client.get(f"/jobs/{jobs['prior']}/cameras").json()["frames"][3]
    response = client.get(frame["image_url"])
    assert response.status_code == 200 and response.headers["content-type"] == "image/png"
    assert response.content == (tiny_rooms["prior"] / frame["name"]).read_bytes()


@pytest.mark.parametrize("index", ["7", "-1", "..%2Ftransforms.json"])
def test_a_camera_the_scene_lacks_has_no_image(api, index):
    client, _settings, jobs = api
    assert client.get(f"/jobs/{jobs['prior']}/cameras/{index}/image").status_code in (404, 422)


def test_an_unknown_job_has_no_cameras(api):
    client, _settings, _jobs = api
    response = client.get(f"/jobs/{'d' * 32}/cameras")
    assert response.status_code == 404 and "no job" in response.json()["detail"]


def test_a_scene_that_cannot_be_read_is_503_naming_it(api):
    client, settings, jobs = api
    scene_id = jobstore.JOBS.get(settings, jobs["bare"]).scene_id
    (settings.scenes_dir / scene_id / "transforms.json").unlink()
    response = client.get(f"/jobs/{jobs['bare']}/cameras")
    assert response.status_code == 503 and scene_id in response.json()["detail"]


def test_the_cameras_need_the_token(api):
    client, _settings, jobs = api
    assert client.get(f"/jobs/{jobs['prior']}/cameras", headers={"Authorization": ""}).status_code == 401


def _keyframe_body(client, job_id: str, **overrides) -> dict:
    frames = client.get(f"/jobs/{job_id}/cameras").json()["frames"]
    camera = {k: frames[0][k] for k in ("width", "height", "fl_x", "fl_y", "cx", "cy")}
    keys = [frames[0]["transform_matrix"], frames[3]["transform_matrix"], frames[6]["transform_matrix"]]
    return {"keyframes": keys, "frames": 12, "fps": 6, **camera, **overrides}


def test_keyframes_become_a_path_through_each_of_them(api):
    client, _settings, jobs = api
    body = _keyframe_body(client, jobs["prior"])
    made = client.post("/camera-paths", json=body).json()
    poses = np.asarray([f["transform_matrix"] for f in made["frames"]])
    assert len(poses) == 12 and made["fps"] == 6 and (made["width"], made["height"]) == (24, 18)
    for key in body["keyframes"]:  # every keyframe is one of the path's frames
        assert np.abs(poses - np.asarray(key)).max(axis=(1, 2)).min() < 1e-9
    parsed = parse_nerfstudio(made["camera_path"])  # what POST /jobs/{id}/videos takes
    np.testing.assert_allclose(parsed.poses, poses, atol=1e-9)


def test_a_nerfstudio_path_is_read_back_in_scene_units(api):
    client, _settings, jobs = api
    made = client.post("/camera-paths", json=_keyframe_body(client, jobs["prior"])).json()
    again = client.post("/camera-paths", json={"camera_path": made["camera_path"]}).json()
    np.testing.assert_allclose([f["transform_matrix"] for f in again["frames"]],
                               [f["transform_matrix"] for f in made["frames"]], atol=1e-9)


@pytest.mark.parametrize(
    ("overrides", "detail"),
    [
        ({"keyframes": None}, "give keyframes"),
        ({"camera_path": {"camera_path": []}}, "not both"),
        ({"fl_x": None}, "keyframes need"),
        ({"frames": 2}, "cannot pass through"),
        ({"frames": 10_000}, "exceeds the limit"),
        ({"width": 8000, "height": 8000}, "exceeds the limit"),
    ],
)
def test_a_bad_keyframe_request_is_422_naming_the_problem(api, overrides, detail):
    client, _settings, jobs = api
    response = client.post("/camera-paths", json=_keyframe_body(client, jobs["prior"], **overrides))
    assert response.status_code == 422 and detail in json.dumps(response.json()["detail"])


def test_a_keyframe_that_is_no_pose_is_refused_naming_it(api):
    client, _settings, jobs = api
    body = _keyframe_body(client, jobs["prior"])
    body["keyframes"][1] = [[2.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 2.0, 0], [0, 0, 0, 1]]  # a scale, no rotation
    response = client.post("/camera-paths", json=body)
    assert response.status_code == 422 and "poses[1]" in response.json()["detail"]


def test_a_bad_nerfstudio_path_is_422_naming_the_key(api):
    client, _settings, _jobs = api
    path = {"render_width": 24, "render_height": 18, "fps": 6, "camera_path": [{"camera_to_world": [1, 2]}]}
    response = client.post("/camera-paths", json={"camera_path": path})
    assert response.status_code == 422 and "camera_path[0]" in response.json()["detail"]


# ------------------------------------------------------------------------------------------------ the page


@pytest.fixture(scope="module")
def trained(tmp_path_factory, small_room):
    """A service on its embedded default (token set) with a short job trained on the small room: (service, job
    id). The page is the same on either broker; renders and videos through Redis are tests/service/test_service.py's
    and test_service_outputs.py's."""
    svc = start_service(tmp_path_factory.mktemp("viewer") / "service", token=TOKEN)
    try:
        yield svc, _trained_job(svc, small_room)
    finally:
        svc.stop()


def _trained_job(svc, scene_dir) -> str:
    """The id of a short job trained on ``scene_dir`` in ``svc`` (succeeded)."""
    with svc.client() as client:
        scene = client.post("/scenes", files={"file": ("room.zip", zip_scene(scene_dir), "application/zip")})
        assert scene.status_code == 201, scene.text
        job = client.post(f"/scenes/{scene.json()['id']}/jobs", json={"max_seconds": 8, "compile": False}).json()
        wait_for(lambda: client.get(f"/jobs/{job['id']}").json()["state"] in ("succeeded", "failed"), 600,
                 "the job to finish", 1.0)
        assert client.get(f"/jobs/{job['id']}").json()["state"] == "succeeded", svc.logs()
    return job["id"]


@pytest.fixture
def page():
    with browser_page(1300, 850) as opened:
        yield opened


class RenderLog:
    """Every POST /render the page sent and was answered: its JSON body and its response, in order."""

    def __init__(self, page) -> None:
        self.page = page
        self.calls: list[tuple[dict, object]] = []
        page.on("response", self._record)

    def _record(self, response) -> None:
        if response.url.endswith("/render") and response.request.method == "POST" and response.ok:
            self.calls.append((response.request.post_data_json, response))

    def shown(self) -> tuple[dict, bytes]:
        """The request body and response bytes of the frame on the page's screen (its response event may
        still be on its way to this process: playwright delivers events while a page call waits)."""
        body = self.page.evaluate("() => window.viewerState.frames.shownBody")
        for _ in range(600):
            found = [response for sent, response in self.calls if sent == body]
            if found:
                return body, found[-1].body()
            self.page.wait_for_timeout(50)
        raise AssertionError(f"no response recorded for the shown frame {body}")


SETTLED = """() => { const s = window.viewerState; return s && !s.frames.inflight
  && s.frames.shownKey === s.currentKey() && s.frames.shownQuality === (s.view.mode === "rgb" ? "final" : "full"); }"""


def _settle(page) -> None:
    """Wait until the last frame of the current view is on screen: full size, antialiased for colour."""
    page.wait_for_function(SETTLED, timeout=60_000)


def _canvas_rgb(page) -> np.ndarray:
    rgba = page.evaluate("""() => { const c = document.getElementById("render");
      return Array.from(c.getContext("2d").getImageData(0, 0, c.width, c.height).data); }""")
    size = page.evaluate("() => [document.getElementById('render').width, document.getElementById('render').height]")
    return np.asarray(rgba, dtype=np.uint8).reshape(size[1], size[0], 4)[..., :3]


def _drag(page, dx: int, dy: int) -> None:
    box = page.locator("#stage").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx, y + dy, steps=6)
    page.mouse.up()


@pytest.mark.slow
def test_the_viewer_renders_drags_snaps_and_starts_a_video(trained, page, tmp_path):
    svc, job_id = trained
    csp = csp_reports(page)
    renders = RenderLog(page)
    page.goto(f"{svc.base_url}/")  # the dashboard keeps the token; the job's row links to its viewer
    page.wait_for_selector("text=needs an API token")
    page.fill("#token", TOKEN)
    page.click("#token-form button")
    page.click(f'tr[data-job-id="{job_id}"] a.viewer-link', timeout=60_000)
    page.wait_for_url(f"**/static/viewer.html?job={job_id}")
    _settle(page)
    first_body, first_image = renders.shown()
    page.screenshot(path=str(tmp_path / "viewer-first-camera.png"))

    # a drag: a small frame while moving, then the full frame of a new pose
    _drag(page, 80, 25)
    page.screenshot(path=str(tmp_path / "viewer-moving.png"))  # the stale frame faded, the prior drawn over it
    _settle(page)
    moved_body, moved_image = renders.shown()
    assert moved_body["transform_matrix"] != first_body["transform_matrix"] and moved_image != first_image
    small = [body for body, _ in renders.calls if body["width"] < moved_body["width"]]
    assert small  # a small frame was asked; small and full frames with one ray per pixel, the final one antialiased
    assert all(body["antialias"] is False for body in small) and "antialias" not in moved_body
    full = [body for body, _ in renders.calls if body["width"] == moved_body["width"] and "antialias" in body]
    assert full and all(body["antialias"] is False for body in full)
    page.screenshot(path=str(tmp_path / "viewer-dragged.png"))

    # fly: W moves the camera forward (along -Z of its pose), turning nothing
    page.focus("#stage")
    page.keyboard.down("w")
    page.wait_for_timeout(300)
    page.keyboard.up("w")
    _settle(page)
    flown = np.asarray(renders.shown()[0]["transform_matrix"])
    before = np.asarray(moved_body["transform_matrix"])
    step = flown[:3, 3] - before[:3, 3]
    assert np.linalg.norm(step) > 0 and step @ -before[:3, 2] > 0.99 * np.linalg.norm(step)
    np.testing.assert_allclose(flown[:3, :3], before[:3, :3], atol=1e-9)

    # snap to an evaluation camera: the shown pixels are POST /render's of the same pose, ground truth beside
    with svc.client() as client:
        cameras = client.get(f"/jobs/{job_id}/cameras").json()["frames"]
        evaluation = next(f for f in cameras if "train" not in f["splits"])
        page.select_option("#camera-select", str(evaluation["index"]))
        page.click("#camera-snap")
        _settle(page)
        body, image = renders.shown()
        assert body["transform_matrix"] == evaluation["transform_matrix"] and body["width"] == evaluation["width"]
        direct = client.post("/render", json=body)
        assert direct.status_code == 200 and direct.content == image
        # which checkpoint rendered, through either broker's outcome: the succeeded job's last one
        finished = client.get(f"/jobs/{job_id}").json()
        assert int(direct.headers["X-VoxNeRF-Iteration"]) == finished["checkpoint_iteration"] == finished["iteration"]
        assert direct.headers["X-VoxNeRF-Job-State"] == "succeeded" and "X-VoxNeRF-Partial" not in direct.headers
    assert page.inner_text("#checkpoint") == f"iteration {finished['iteration']}"
    expected = np.asarray(Image.open(io.BytesIO(direct.content)).convert("RGB"))
    np.testing.assert_array_equal(_canvas_rgb(page), expected)
    page.wait_for_function("() => document.getElementById('gt-image').naturalWidth > 0", timeout=30_000)
    page.screenshot(path=str(tmp_path / "viewer-snapped.png"))

    # depth with its colour bar in metres (the room has sensor depth)
    page.check('input[name="output"][value="depth"]')
    _settle(page)
    assert renders.shown()[0]["outputs"] == ["depth"]
    assert page.is_visible("#colorbar-box") and "m" in page.inner_text("#bar-units")
    low, high = float(page.inner_text("#bar-min")), float(page.inner_text("#bar-max"))
    assert 0 < low < high < 20
    page.screenshot(path=str(tmp_path / "viewer-depth.png"))
    page.check('input[name="output"][value="rgb"]')

    # two keyframes, exported and imported again, then a video of the path
    page.click("#key-add")
    _drag(page, -60, 0)
    _settle(page)
    page.click("#key-add")
    page.fill("#path-frames", "8")
    page.fill("#path-fps", "8")
    with page.expect_download() as download:
        page.click("#path-export")
    exported = json.loads(Path(download.value.path()).read_text())
    assert len(exported["camera_path"]) == 8 and len(exported["voxnerf_keyframes"]) == 2
    # Chromium under load may stamp a frame before the click that asked for it: every frame here comes 1 s early
    page.evaluate("() => { const raf = window.requestAnimationFrame.bind(window);"
                  " window.requestAnimationFrame = (step) => raf((now) => step(now - 1000)); }")
    page.click("#path-preview")  # plays the path: the view ends at its last frame, the second keyframe
    page.wait_for_function("() => window.viewerState.path.frames && !window.viewerState.path.playing", timeout=30_000)
    _settle(page)
    last = np.asarray(exported["camera_path"][-1]["camera_to_world"]).reshape(4, 4)
    np.testing.assert_allclose(renders.shown()[0]["transform_matrix"], last, atol=1e-9)
    page.click("#key-clear")
    page.set_input_files("#path-import", str(download.value.path()))
    page.wait_for_function("() => document.querySelectorAll('#keyframes li').length === 2", timeout=30_000)
    page.click("#path-video")
    page.wait_for_selector("#videos li[data-output-id]", timeout=30_000)
    with svc.client() as client:
        outputs = client.get(f"/jobs/{job_id}/outputs").json()
    assert [(o["kind"], o["params"]["camera_path"]["frames"]) for o in outputs] == [("video", 8)]
    page.screenshot(path=str(tmp_path / "viewer-keyframes.png"), full_page=True)
    assert csp == [], csp
    print(f"viewer screenshots: {tmp_path}")
