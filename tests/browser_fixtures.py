"""A real headless browser for the page tests: playwright driving Debian's /usr/bin/chromium (no download).

``browser_page`` opens one page; ``csp_reports`` collects the Content-Security-Policy violations Chromium
reports in the page's console (the service's policy allows no inline script or style, no CDN).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

CHROMIUM = Path("/usr/bin/chromium")


@contextmanager
def browser_page(width: int, height: int, **options) -> Iterator:
    """A new page of a fresh headless Chromium (``options``: more of playwright's ``new_page`` arguments);
    skips the test where playwright or Debian's chromium is missing."""
    sync_api = pytest.importorskip("playwright.sync_api")
    if not CHROMIUM.exists():
        pytest.skip("Debian's chromium is not installed (scripts/install.sh installs it)")
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            yield browser.new_page(viewport={"width": width, "height": height}, **options)
        finally:
            browser.close()


def csp_reports(page) -> list[str]:
    """A list that fills with each Content-Security-Policy violation the page reports from now on."""
    reports: list[str] = []
    page.on("console", lambda m: "Content Security Policy" in m.text and reports.append(m.text))
    return reports


STILL_JS = """([selector, quietMs]) => {
  const node = document.querySelector(selector);
  if (!node) return false;
  const box = node.getBoundingClientRect();
  const key = [box.x, box.y, box.width, box.height].join(",");
  const seen = (window.__stillBoxes = window.__stillBoxes || {});
  const now = performance.now();
  if (!seen[selector] || seen[selector].key !== key) {
    seen[selector] = { key, since: now };
    return false;
  }
  return now - seen[selector].since >= quietMs;
}"""


def click_when_still(page, selector: str, quiet_ms: int = 750, timeout_ms: int = 60_000) -> None:
    """Click ``selector`` once its box has not moved for ``quiet_ms``. Playwright's own stability check spans
    two animation frames: on a dashboard whose rows above the element grow as their images arrive one by one, a
    click can land where the element was a moment before, and miss it."""
    page.wait_for_function(STILL_JS, arg=[selector, quiet_ms], timeout=timeout_ms)
    page.click(selector)
