"""The API reference pages in a real headless browser (playwright driving Debian's chromium): with the token the
dashboard saved, ``/docs`` (Swagger UI) lists every operation and its "Try it out" reaches the API with the
token, ``/redoc`` lists them too; every request the browser makes goes to the service's own host (scripts,
styles, fonts, the schema), and the service's Content-Security-Policy reports no violation. Without a token the
page says the schema needs one."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest
from browser_fixtures import browser_page, csp_reports
from service_fixtures import start_service

pytestmark = pytest.mark.slow

TOKEN = "reference-token"


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("reference"), token=TOKEN, workers=False)
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture
def page():
    with browser_page(1400, 900) as opened:
        yield opened


def _operations(service) -> list[tuple[str, str, str]]:
    """``(METHOD, path, summary)`` of every operation of the service's schema."""
    with service.client() as client:
        schema = client.get("/openapi.json").json()
    return [(method.upper(), path, op["summary"])
            for path, ops in schema["paths"].items() for method, op in ops.items()]


def _requests(page) -> list[str]:
    """A list that fills with the URL of every request the page makes from now on."""
    urls: list[str] = []
    page.on("request", lambda request: urls.append(request.url))
    return urls


def _foreign(urls: list[str], base_url: str) -> list[str]:
    own = urlsplit(base_url).netloc
    return [url for url in urls if urlsplit(url).scheme not in ("blob", "data") and urlsplit(url).netloc != own]


def _save_token_on_the_dashboard(page, base_url: str) -> None:
    page.goto(base_url + "/")
    page.fill("#token", TOKEN)
    page.click("#token-form button")


def test_swagger_ui_lists_every_operation_and_tries_one_with_the_token(service, page):
    operations = _operations(service)
    urls, csp = _requests(page), csp_reports(page)
    _save_token_on_the_dashboard(page, service.base_url)
    page.goto(service.base_url + "/docs")
    page.wait_for_selector(".opblock", timeout=60_000)
    shown = page.eval_on_selector_all(
        ".opblock", "blocks => blocks.map(b => [b.querySelector('.opblock-summary-method').textContent, "
        "b.querySelector('.opblock-summary-path').dataset.path])")
    assert sorted(map(tuple, shown)) == sorted((method, path) for method, path, _ in operations)

    block = page.locator(".opblock-get", has=page.locator('[data-path="/jobs"]')).first
    block.locator(".opblock-summary").click()
    block.locator("button.try-out__btn").click()
    block.locator("button.execute").click()
    status = block.locator(".live-responses-table tbody .response-col_status").first
    status.wait_for(timeout=30_000)
    assert status.inner_text().strip() == "200"  # the request carried the token: 401 without it

    assert _foreign(urls, service.base_url) == []
    assert csp == [], csp


def test_redoc_lists_every_operation_with_nothing_from_outside(service, page):
    operations = _operations(service)
    urls, csp = _requests(page), csp_reports(page)
    _save_token_on_the_dashboard(page, service.base_url)
    page.goto(service.base_url + "/redoc")
    page.wait_for_selector("[data-loaded=true]", timeout=60_000)
    page.wait_for_selector("li[data-item-id*='/operation/']", state="attached", timeout=60_000)
    assert page.locator("li[data-item-id*='/operation/']").count() == len(operations)  # the side menu
    headings = set(page.eval_on_selector_all("h2", "hs => hs.map(h => h.textContent.trim())"))
    assert {summary for _, _, summary in operations} <= headings  # each operation's section
    assert _foreign(urls, service.base_url) == []
    assert not any("fonts.g" in url for url in urls)
    assert csp == [], csp


def test_without_a_token_the_page_asks_for_one(service, page):
    csp = csp_reports(page)
    page.goto(service.base_url + "/docs")
    page.wait_for_selector("text=needs an API token", timeout=30_000)
    assert page.locator(".opblock").count() == 0
    assert csp == [], csp
