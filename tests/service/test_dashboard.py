"""The dashboard in a real headless browser (playwright driving Debian's /usr/bin/chromium, no download):
with the API token entered, a training job's progress bar advances, its PSNR plot and evaluation thumbnails
appear, a pose of the finished job renders, and a video started from its row plays in the page with the asked
size and duration. A screenshot is saved under the test's temporary directory."""

from __future__ import annotations

import json

import pytest
from browser_fixtures import browser_page, click_when_still, csp_reports
from service_fixtures import first_pose, start_service, zip_scene

pytestmark = pytest.mark.slow

TOKEN = "dash-token"


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("dashboard"), token=TOKEN)
    try:
        svc.start_worker("outputs")
        yield svc
    finally:
        svc.stop()


@pytest.fixture
def page():
    with browser_page(1400, 900) as opened:
        yield opened


def test_dashboard_shows_live_progress_plot_thumbnails_and_renders(service, page, small_room, tmp_path):
    with service.client() as client:
        scene = client.post(
            "/scenes", files={"file": ("room.zip", zip_scene(small_room), "application/zip")}
        ).json()
        # progress evaluations at 4 (and 8) s of training, then the final one: the plot's two points at least
        job = client.post(
            f"/scenes/{scene['id']}/jobs", json={"max_seconds": 12, "compile": False, "eval_every_s": 4.0}
        ).json()

    csp = csp_reports(page)
    page.goto(service.base_url + "/")
    page.wait_for_selector("text=needs an API token")  # no token yet: the dashboard asks for it
    page.fill("#token", TOKEN)
    page.click("#token-form button")
    row = f'tr[data-job-id="{job["id"]}"]'
    bar = f"{row} [role=progressbar]"
    page.wait_for_selector(bar, timeout=60_000)
    assert page.inner_text(f"{row} .col-by") == "admin"  # who started it: VOXNERF_API_TOKEN's principal

    values = []

    def progress() -> int:
        return int(page.get_attribute(bar, "aria-valuenow"))

    page.wait_for_function(
        f"() => Number(document.querySelector('{bar}').getAttribute('aria-valuenow')) > 0", timeout=240_000
    )
    values.append(progress())
    page.wait_for_selector(f'{row}[data-state="succeeded"]', timeout=420_000)
    values.append(progress())
    assert values[0] > 0 and values[-1] == 100 and values == sorted(values)

    page.wait_for_selector(f"{row} .plot polyline", timeout=30_000)
    assert int(page.get_attribute(f"{row} .plot", "data-points")) >= 2
    page.wait_for_function(
        f"() => [...document.querySelectorAll('{row} .thumbs img')]"
        ".filter(i => i.naturalWidth > 0).length >= 2",
        timeout=60_000,
    )

    page.select_option("#render-job", job["id"])
    page.fill("#render-pose", json.dumps(first_pose(small_room)))
    click_when_still(page, "#render-form button")  # the row above still grows as its thumbnails arrive
    page.wait_for_function(
        "() => document.getElementById('render-image').naturalWidth === 64", timeout=60_000
    )
    assert page.is_hidden("#message") or "refused" not in page.inner_text("#message")

    # a video of the finished job from its row's button, played from a blob URL: 6 frames at 12 fps, 32x24
    page.fill("#video-frames", "6")
    page.fill("#video-fps", "12")
    page.fill("#video-width", "32")
    page.fill("#video-height", "24")
    page.click(f'{row} button[data-output="orbit"]')
    video = f'{row} li[data-kind="video"][data-state="succeeded"] video'
    page.wait_for_selector(video, timeout=240_000)
    page.wait_for_function(f"() => document.querySelector('{video}').readyState >= 1", timeout=60_000)
    size = page.eval_on_selector(video, "v => [v.videoWidth, v.videoHeight, v.duration]")
    assert size[:2] == [32, 24] and abs(size[2] - 0.5) < 0.05, size

    assert csp == [], csp
    shot = tmp_path / "dashboard.png"
    page.screenshot(path=str(shot), full_page=True)
    assert shot.stat().st_size > 10_000
    print(f"dashboard screenshot: {shot}")


def test_a_bag_uploaded_from_the_dashboard_is_imported_and_its_scene_offered_for_training(service, page, tmp_path):
    from rosbag_fixtures import REDKITCHEN, BagSpec, make_frames, write_bag

    if not (REDKITCHEN / "transforms.json").is_file():
        pytest.skip("shared redkitchen data not present")
    bag = write_bag(tmp_path / "robot.bag", BagSpec(make_frames(step=15, n=6), scale=4), "ros1")
    page.goto(service.base_url + "/")
    page.fill("#token", TOKEN)
    page.click("#token-form button")
    page.set_input_files("#upload-file", str(bag))
    click_when_still(page, "#upload-form button")  # below the jobs table, which grows as earlier jobs' renders load
    try:
        page.wait_for_selector("#message >> text=queued for import", timeout=30_000)
    except Exception:
        pytest.fail(f"the dashboard says {page.inner_text('#message')!r}, not that the bag is queued\n"
                    f"{service.logs()}")
    done = page.wait_for_selector('#imports tr[data-state="succeeded"]', timeout=240_000)
    assert "robot (rosbag)" in done.inner_text() and "frames" in done.inner_text()
    page.wait_for_function("() => [...document.querySelectorAll('#job-scene option')]"
                           ".some((o) => o.textContent.startsWith('robot'))", timeout=10_000)


def test_a_poll_sent_before_the_token_was_saved_is_sent_again_with_it(service, page):
    # the dashboard polls its imports every second: one sent without a token and answered after Save must not
    # tell the user to enter the token they just saved
    held = []

    def hold_first_without_token(route):
        if not held and "authorization" not in route.request.headers:
            held.append(route)  # answered below, after Save
        else:
            route.continue_()

    page.route("**/imports?limit=20", hold_first_without_token)
    page.goto(service.base_url + "/")
    page.wait_for_selector("text=needs an API token")
    page.fill("#token", TOKEN)
    page.click("#token-form button")
    asks = ("() => { const m = document.getElementById('message');"
            " return !m.hidden && m.textContent.includes('needs an API token'); }")
    try:
        page.wait_for_function(f"() => !({asks})()")  # Save took the request for a token away
    except Exception:
        pytest.fail(f"after Save the dashboard still says {page.inner_text('#message')!r}")
    with page.expect_response(lambda r: r.request == held[0].request) as answered:
        held[0].continue_()
    assert answered.value.status == 401  # it carried no token
    page.wait_for_timeout(500)
    # other messages (an earlier job's renders loading on a loaded machine) are not this test's
    assert not page.evaluate(f"({asks})()"), page.inner_text("#message")
