"""The console's browser tests' one browser: Playwright (from PyPI) driving Debian's chromium
(``executable_path=/usr/bin/chromium``). Skipped where either is missing, failed in CI."""
from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]


@contextlib.contextmanager
def launch() -> Iterator[Any]:
    """A headless chromium (the ``browser`` fixture of tests/conftest.py)."""
    missing = None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing = "playwright is not installed (pip install playwright)"
    if missing is None and not (os.path.exists(CHROMIUM) or shutil.which("chromium")):
        missing = "Debian's chromium is not installed (scripts/setup.sh --tools)"
    if missing:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(missing)
        pytest.skip(missing)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def wait_js(page, expr, timeout_s=60.0):
    """Wait until ``expr`` is true in the page (the page's CSP forbids eval, which Playwright's
    wait_for_function needs: open the context with ``bypass_csp=True``)."""
    page.wait_for_function(expr, timeout=timeout_s * 1000, polling=250)
