"""Open a report page in a real browser (Chromium, headless, driven by Playwright) and say what
it shows. Chromium is Debian's (``/usr/bin/chromium``; .ci/run installs it); Playwright's own
browser download is never used. Outside CI a machine without either skips; in CI (``CI`` set)
a missing browser is a failure, so the page is always checked there."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]


def browser_or_skip():
    """Playwright's ``sync_playwright`` when it and Chromium are here (else skip, or fail in CI)."""
    missing = None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing = "playwright is not installed (pip install -e '.[dev]')"
    if missing is None and not os.path.exists(CHROMIUM):
        missing = f"no Chromium at {CHROMIUM} (apt-get install chromium)"
    if missing:
        if os.environ.get("CI"):
            pytest.fail(missing)
        pytest.skip(missing)
    return sync_playwright


def launch(playwright):
    return playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)


def open_page(browser, page_path: Path, requests: list[str], width: int = 1280, height: int = 900):
    """A tab showing ``page_path``; every request the page makes other than for itself and its
    data: URIs is recorded in ``requests`` and refused."""
    page = browser.new_page(viewport={"width": width, "height": height})
    url = page_path.resolve().as_uri()

    def guard(route):
        if route.request.url != url and not route.request.url.startswith("data:"):
            route.abort()  # recorded by the "request" listener below
        else:
            route.continue_()

    page.route("**/*", guard)
    page.on("request", lambda r: None if (r.url == url or r.url.startswith("data:")) else requests.append(r.url))
    page.goto(url, wait_until="load")
    return page
