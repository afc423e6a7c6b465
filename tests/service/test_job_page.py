"""The job and scene pages in a real headless browser (playwright driving Debian's /usr/bin/chromium, as
tests/service/test_dashboard.py does): from the dashboard's job row to the job page of a 35 s job, whose error plot has
more than one PSNR point per split while the job still runs and a training-loss curve. The points are the
front-loaded progress evaluation at 10 s of training (the default eval_every_s of 60 s alone would give none before
the final evaluation; the first one is sized from a fixed cost per ray, so it runs on any machine) and the job's
``eval_at`` evaluation at 20 s, which runs whatever the machine's load, where a loaded machine leaves the later
progress evaluations, sized to 2 % of max_seconds, too few rays to run. Once it succeeded: the stages with their
reasons, the final metrics, the per-view table with each render beside its ground truth, the resolved config and the
report download; then the scene page. Screenshots are saved under the test's temporary directory."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from browser_fixtures import browser_page, csp_reports
from service_fixtures import start_service, zip_scene

pytestmark = pytest.mark.slow

TOKEN = "job-page-token"
JOB_SECONDS = 35
EVAL_AT = [20]  # a full evaluation, uncharged and never skipped, drawn with 15 s of training still to come
SET_UP_STAGES = ("load_scene", "prior", "octree", "pseudo_depth", "first_hit_cache")

# Checked in one go in the page: the page follows the job's events, so the next one (the final state) may be drawn
# right after.
RUNNING_WITH_TWO_POINTS_PER_SPLIT = """() => {
  const lines = [...document.querySelectorAll('#psnr-plot polyline')];
  const bar = document.querySelector('#summary [role=progressbar]');
  const eta = document.querySelector('#summary dd[data-fact="ETA"]');
  return document.body.dataset.state === 'running' && lines.length >= 2
    && lines.every((line) => Number(line.dataset.points) >= 2) && bar !== null && eta.textContent !== '–';
}"""


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("job_page"), token=TOKEN)
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture
def page():
    with browser_page(1300, 900, accept_downloads=True) as opened:
        yield opened


def test_the_job_page_shows_the_run_live_then_its_results(service, page, small_room, tmp_path):
    with service.client() as client:
        scene = client.post(
            "/scenes", files={"file": ("room.zip", zip_scene(small_room), "application/zip")}
        ).json()
        options = {"max_seconds": JOB_SECONDS, "eval_at": EVAL_AT, "compile": False}
        job = client.post(f"/scenes/{scene['id']}/jobs", json=options).json()

    csp = csp_reports(page)
    page.goto(service.base_url + "/")
    page.fill("#token", TOKEN)
    page.click("#token-form button")
    page.click(f'tr[data-job-id="{job["id"]}"] a.job-page', timeout=30_000)
    page.wait_for_url(f"**/static/job.html?id={job['id']}")

    # while it runs: more than one PSNR point per split, and a loss curve filled in every second
    page.wait_for_function(RUNNING_WITH_TWO_POINTS_PER_SPLIT, timeout=180_000)
    splits = page.eval_on_selector_all("#psnr-plot polyline", "ls => ls.map(l => l.dataset.series)")
    assert set(splits) == {"interpolation", "extrapolation"}, splits
    assert int(page.get_attribute("#loss-plot polyline", "data-points")) >= 5
    page.screenshot(path=str(tmp_path / "job-running.png"), full_page=True)

    page.wait_for_selector('body[data-state="succeeded"]', timeout=300_000)

    # the stages that ran and why
    stages = page.eval_on_selector_all(
        "#stages tbody tr",
        "rows => rows.map(r => [r.dataset.stage, r.dataset.ran, r.querySelector('.why').textContent])",
    )
    names = [name for name, _, _ in stages]
    assert set(SET_UP_STAGES) <= set(names) and {"progress_evals", "train", "final_eval"} <= set(names), names
    assert all(why.strip() for _, _, why in stages), stages
    progress_why = next(why for name, _, why in stages if name == "progress_evals")
    assert re.match(r"\d+ progress evaluations? at [\d, ]+ s of training, of [\d-]+ rays over up to 4 views per split",
                    progress_why), progress_why

    # final metrics per split, and every view's render beside its ground truth
    assert set(page.eval_on_selector_all("#metrics tbody tr", "rows => rows.map(r => r.dataset.split)")) == set(splits)
    views = page.eval_on_selector_all("#views tbody tr", "rows => rows.length")
    with service.client() as client:
        metrics = client.get(f"/jobs/{job['id']}").json()["metrics"]
    assert views == sum(len(m["views"]) for m in metrics.values()) and views >= 2
    page.wait_for_function(
        "n => ['render', 'truth'].every(kind => [...document.querySelectorAll(`#views img[data-kind=${kind}]`)]"
        ".filter(img => img.naturalWidth === 64).length === n)",
        arg=views, timeout=60_000,
    )

    # the config: the job's options, and report.json's resolved config with those options marked
    assert page.get_attribute('#options tr[data-key="max_seconds"]', "data-key") == "max_seconds"
    page.wait_for_selector('#config tr.set[data-key="max_seconds"]', timeout=30_000)
    assert page.eval_on_selector_all("#config tbody tr", "rows => rows.length") > 20
    with page.expect_download() as download:
        page.click('#files a[data-path$="/report"]')
    report = json.loads(Path(download.value.path()).read_text())
    assert report["status"] == "succeeded" and report["loss_series"] and report["config"]["max_seconds"] == JOB_SECONDS
    assert page.is_visible('#files a[data-path$="/checkpoint"]')
    page.screenshot(path=str(tmp_path / "job-succeeded.png"), full_page=True)

    # the scene page: its summary and its jobs
    page.click("#scene-link")
    page.wait_for_selector(f'#jobs tr[data-job-id="{job["id"]}"][data-state="succeeded"]', timeout=30_000)
    assert page.inner_text('#summary dd[data-fact="Frames"]') == str(scene["summary"]["frames"])
    assert "sigma" in page.inner_text('#summary dd[data-fact="Prior"]')
    assert page.inner_text('#splits tr[data-split="train"] td') == str(scene["summary"]["splits"]["train"])
    page.screenshot(path=str(tmp_path / "scene.png"), full_page=True)

    assert csp == [], csp
    for name in ("job-running.png", "job-succeeded.png", "scene.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    print(f"job page screenshots: {tmp_path}")
