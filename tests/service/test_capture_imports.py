"""Captures whose import is queued (ROS bags, Stray Scanner recordings): ``POST /scenes`` answers 202 with the import,
a real train worker imports it on the lease lifecycle, and the scene exists once the import has succeeded; refusals,
cancel and the queue limit. Real HTTP through uvicorn and real Celery workers; bags and recordings made from
redkitchen (tests/rosbag_fixtures, tests/phone_app_fixtures)."""

from __future__ import annotations

from pathlib import Path

import pytest
from capture_fixtures import redkitchen_rgb, write_redkitchen_photos, write_video
from phone_app_fixtures import redkitchen_frames, write_stray
from rosbag_fixtures import REDKITCHEN, BagSpec, make_frames, write_bag
from service_fixtures import FINAL_STATES, start_service, wait_for, wait_until_final, zip_scene

pytestmark = [
    pytest.mark.skipif(not (REDKITCHEN / "transforms.json").is_file(), reason="shared redkitchen data not present"),
    pytest.mark.timeout(600),
]


@pytest.fixture(scope="module")
def frames():
    return make_frames(step=5, n=8)


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    service = start_service(tmp_path_factory.mktemp("capture_imports"))
    yield service
    service.stop()


@pytest.fixture(scope="module")
def client(service):
    with service.client(timeout_s=120) as c:
        yield c


def _storage(folder: Path) -> Path:
    """The one .mcap / .db3 file of a ROS 2 bag folder."""
    (storage,) = [p for p in folder.iterdir() if p.suffix in (".mcap", ".db3")]
    return storage




def test_a_bag_sent_as_one_file_is_imported_by_a_worker_into_a_scene_that_trains(client, service, frames, tmp_path):
    bag = _storage(write_bag(tmp_path / "kitchen", BagSpec(frames, scale=4), "mcap"))
    response = client.post("/scenes", files={"file": ("kitchen.mcap", bag.read_bytes())}, data={"name": "robot"})
    assert response.status_code == 202, response.text
    queued = response.json()
    assert response.headers["location"] == f"/imports/{queued['id']}"
    assert (queued["layout"], queued["name"], queued["scene_id"]) == ("rosbag", "robot", None)
    assert queued["created_by"] == "local"  # the principal of a tokenless service's loopback clients
    assert queued["size_bytes"] == bag.stat().st_size
    done = wait_until_final(service, client, f"/imports/{queued['id']}", 300)
    assert (done["state"], done["stage"], done["progress"], done["error"]) == ("succeeded", "done", 1.0, None)
    assert done["summary"]["format"] == "rosbag" and done["summary"]["frames"] >= 2
    assert done["scene_url"] == f"/scenes/{done['scene_id']}"
    scene = client.get(done["scene_url"]).json()
    assert scene["name"] == "robot" and scene["imported"]["format"] == "rosbag"
    assert scene["created_by"] == "local"  # the worker made the scene in the name of the import's maker
    assert scene["summary"]["frames"] == done["summary"]["frames"] and scene["summary"]["depth"]
    assert not list((service.data_dir / "imports").iterdir())  # the raw capture went with the import
    job = client.post(f"/scenes/{done['scene_id']}/jobs", json={"max_iters": 2, "compile": False}).json()
    trained = wait_until_final(service, client, f"/jobs/{job['id']}", 300)
    assert trained["state"] == "succeeded", trained


def test_a_zipped_ros2_bag_folder_is_queued_and_takes_the_paper_splits(client, service, tmp_path):
    folder = write_bag(tmp_path / "kitchen", BagSpec(make_frames(step=15, n=66), scale=8), "sqlite3")
    response = client.post("/scenes", files={"file": ("kitchen.zip", zip_scene(folder, "kitchen"))},
                           data={"splits": "paper"})
    assert response.status_code == 202, response.text
    assert response.json()["params"] == {"splits": "paper"}
    done = wait_until_final(service, client, f"/imports/{response.json()['id']}", 300)
    assert done["state"] == "succeeded", done["error"]
    assert done["summary"]["splits"]["extrapolation"] > 0
    scene = client.get(done["scene_url"]).json()
    assert scene["summary"]["splits"]["extrapolation"] == done["summary"]["splits"]["extrapolation"]


def test_a_zipped_stray_scanner_recording_is_queued_and_imported_with_its_depth(client, service, tmp_path):
    recording = write_stray(tmp_path / "stray", redkitchen_frames(12))
    response = client.post("/scenes", files={"file": ("phone.zip", zip_scene(recording, "phone"))})
    assert response.status_code == 202, response.text
    assert response.json()["layout"] == "stray"
    done = wait_until_final(service, client, f"/imports/{response.json()['id']}", 300)
    assert done["state"] == "succeeded", done["error"]
    assert done["summary"]["format"] == "stray" and done["summary"]["depth_frames"] > 0
    assert client.get(done["scene_url"]).json()["summary"]["depth"]


def test_a_zip_of_photos_is_posed_by_structure_from_motion_in_a_worker(client, service, tmp_path):
    photos = write_redkitchen_photos(tmp_path / "photos", range(0, 60, 3))
    response = client.post("/scenes", files={"file": ("kitchen.zip", zip_scene(photos, "kitchen"))})
    assert response.status_code == 202, response.text
    assert response.json()["layout"] == "images"
    seen = []  # (stage, step, progress) while it runs
    done = wait_for(lambda: (row := client.get(f"/imports/{response.json()['id']}").json(),
                             seen.append((row["stage"], row["step"], row["progress"])))[0]["state"] in FINAL_STATES
                    and row, 300, "the photos' import", 0.2)
    assert done["state"] == "succeeded", done["error"]
    steps = [(step, progress) for stage, step, progress in seen if stage == "importing" and step]
    assert steps, seen  # structure from motion said where it was while it ran
    assert all(0.05 <= progress <= 0.8 for _, progress in steps)  # inside the importing stage's share
    assert {step.split(":")[0] for step, _ in steps} <= {"extracting features", "matching features (exhaustive)",
                                                         "registering images", "writing the scene"}
    assert done["step"] is None  # a finished import is not in any step
    # structure from motion repeats itself (one extraction thread, seeded verification and mapper), and the
    # mapper's first seed splits these 20 photos 13 + 7, so a second seed registers them all
    sfm = done["summary"]["sfm"]
    assert done["summary"]["format"] == "images" and sfm["registered"] == 20
    assert sfm["mapping_attempts"] == [{"seed": 0, "registered": 13}, {"seed": 1, "registered": 20}]
    scene = client.get(done["scene_url"]).json()
    assert scene["summary"]["prior"] is not None  # the sparse points, with sigma from the reprojection errors


def test_an_import_cancelled_during_structure_from_motion_stops_there_and_stores_nothing(client, service, tmp_path):
    scenes_before = len(client.get("/scenes").json())
    photos = write_redkitchen_photos(tmp_path / "photos", range(0, 120, 3))
    import_id = client.post("/scenes", files={"file": ("kitchen.zip", zip_scene(photos, "kitchen"))}).json()["id"]
    running = wait_for(lambda: (row := client.get(f"/imports/{import_id}").json())["step"] and row, 300,
                       "structure from motion to report a step", 0.2)
    assert running["state"] == "running" and running["stage"] == "importing"
    assert client.post(f"/imports/{import_id}/cancel").status_code == 202
    done = wait_until_final(service, client, f"/imports/{import_id}", 120)
    assert (done["state"], done["scene_id"]) == ("cancelled", None)
    assert done["progress"] < 0.8  # stopped inside structure from motion, not at the next stage (checking: 0.8)
    assert len(client.get("/scenes").json()) == scenes_before
    assert not list((service.data_dir / "imports").iterdir())
    assert not [p for p in service.data_dir.rglob("*") if ".sfm-" in p.name]  # SfM's work folder went too


def test_a_phone_video_sent_as_one_file_is_picked_and_posed_in_a_worker(client, service, tmp_path):
    video = write_video(tmp_path / "walk.mp4", [redkitchen_rgb(i) for i in range(0, 60, 3)])
    response = client.post("/scenes", files={"file": ("walk.mp4", video.read_bytes())})
    assert response.status_code == 202, response.text
    assert (response.json()["layout"], response.json()["name"]) == ("video", "walk")
    done = wait_until_final(service, client, f"/imports/{response.json()['id']}", 300)
    assert done["state"] == "succeeded", done["error"]
    assert done["summary"]["format"] == "video" and done["summary"]["video"]["frames_picked"] == 20


def test_a_bag_without_a_camera_fails_its_import_naming_the_bag_and_stores_nothing(client, service, frames, tmp_path):
    scenes_before = len(client.get("/scenes").json())
    bag = write_bag(tmp_path / "nocamera.bag", BagSpec(frames[:3], scale=4, colour="none"), "ros1")
    response = client.post("/scenes", files={"file": ("nocamera.bag", bag.read_bytes())})
    assert response.status_code == 202, response.text
    done = wait_until_final(service, client, f"/imports/{response.json()['id']}", 300)
    assert done["state"] == "failed" and done["scene_id"] is None
    assert done["error"].startswith(f"imports/{done['id']}/capture.bag: no camera topic")
    assert "\n" not in done["error"] and str(service.data_dir) not in done["error"]
    assert len(client.get("/scenes").json()) == scenes_before
    assert not list((service.data_dir / "imports").iterdir())


def test_bytes_that_only_start_like_a_bag_fail_as_an_unreadable_bag(client, service, tmp_path):
    response = client.post("/scenes", files={"file": ("x.bag", b"#ROSBAG V2.0\n" + b"\x00" * 64)})
    assert response.status_code == 202, response.text
    done = wait_until_final(service, client, f"/imports/{response.json()['id']}", 300)
    assert done["state"] == "failed" and "not a readable ROS 1 or ROS 2 bag" in done["error"]


def test_imports_are_listed_newest_first_and_unknown_ones_are_404(client):
    listed = client.get("/imports").json()
    assert listed and [row["created_at"] for row in listed] == sorted((r["created_at"] for r in listed), reverse=True)
    assert client.get("/imports?state=failed").json() and all(
        r["state"] == "failed" for r in client.get("/imports?state=failed").json())
    assert client.get("/imports/" + "0" * 32).status_code == 404
    assert client.post("/imports/" + "0" * 32 + "/cancel").status_code == 404


def test_a_queued_import_is_cancelled_at_once_its_capture_removed_and_the_queue_is_bounded(tmp_path, frames):
    """No workers: imports stay queued. The second beyond VOXNERF_MAX_QUEUED_JOBS=1 is a 429 that stores
    nothing; cancelling the queued one ends it and removes its capture; a finished import cannot be cancelled
    again into another state."""
    service = start_service(tmp_path / "svc", workers=False, settings={"VOXNERF_MAX_QUEUED_JOBS": "1"})
    try:
        bag = write_bag(tmp_path / "bag.bag", BagSpec(frames[:3], scale=4), "ros1").read_bytes()
        with service.client() as client:
            first = client.post("/scenes", files={"file": ("a.bag", bag)})
            assert first.status_code == 202 and first.json()["state"] == "queued"
            second = client.post("/scenes", files={"file": ("b.bag", bag)})
            assert second.status_code == 429 and "imports are queued already" in second.json()["detail"]
            imports_dir = service.data_dir / "imports"
            assert [p.name for p in imports_dir.iterdir()] == [first.json()["id"]]
            assert not list((service.data_dir / "staging").iterdir())
            cancelled = client.post(f"/imports/{first.json()['id']}/cancel")
            assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
            assert cancelled.json()["cancelled_by"] == "local"
            assert not list(imports_dir.iterdir())
            assert client.post(f"/imports/{first.json()['id']}/cancel").json()["state"] == "cancelled"
    finally:
        service.stop()
