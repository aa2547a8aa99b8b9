"""The notebook explorer in a real browser: JupyterLab served from a temporary folder,
headless Chromium driven through Playwright. The image must show at the render's
aspect ratio (a 240 x 135 render was once stretched to 320 x 284), change when a slider
moves, and say "rendering..." while a new sky compiles.

Chromium is Playwright's own build (`python -m playwright install chromium`) or the
system's (`chromium` on the PATH, or `$JAXLENS_CHROMIUM`); `make test` tries to install
one (JAXLENS_NO_BROWSER=1 skips both). Without it the test is skipped and says so.
With `$JAXLENS_SCREENSHOTS` set to a folder, the screenshots are saved there too
(docs/images/explorer*.png come from it).
"""

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

if os.environ.get("JAXLENS_NO_BROWSER"):
    pytest.skip("JAXLENS_NO_BROWSER is set: no browser is driven", allow_module_level=True)
pytest.importorskip("ipywidgets", reason="the explorer needs ipywidgets (test extras)")
pytest.importorskip("jupyterlab", reason="the browser test needs jupyterlab (test extras)")
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="the browser test needs playwright (test extras)"
)

TOKEN = "jaxlens-test"
NOTEBOOK = {
    "cells": [{
        "cell_type": "code", "execution_count": None, "metadata": {}, "outputs": [],
        "source": ["import jaxlens as jl\n", "ex = jl.Explorer(240, 135)\n", "ex.widget"],
    }],
    "metadata": {"kernelspec": {"name": "python3", "display_name": "Python 3",
                                "language": "python"}},
    "nbformat": 4, "nbformat_minor": 5,
}  # fmt: skip


def _chromium(playwright) -> str | None:
    candidates = [os.environ.get("JAXLENS_CHROMIUM")]
    candidates += [shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")]
    try:
        candidates.append(playwright.chromium.executable_path)
    except Exception:  # no browsers installed for this Playwright
        pass
    return next((c for c in candidates if c and Path(c).is_file()), None)


@pytest.fixture
def lab(tmp_path, free_port):
    """A JupyterLab server on a free port, serving a notebook that shows an Explorer."""
    (tmp_path / "explorer.ipynb").write_text(json.dumps(NOTEBOOK))
    port = free_port
    cmd = [sys.executable, "-m", "jupyter", "lab", "--no-browser", "--allow-root",
           f"--port={port}", "--ServerApp.ip=127.0.0.1", f"--ServerApp.root_dir={tmp_path}",
           f"--IdentityProvider.token={TOKEN}", "--expose-app-in-browser",
           "--LabApp.news_url=", "--ServerApp.open_browser=False"]  # fmt: skip
    env = dict(os.environ, JAXLENS_CACHE_DIR="", JUPYTER_CONFIG_DIR=str(tmp_path / "config"),
               JUPYTER_RUNTIME_DIR=str(tmp_path / "runtime"))  # fmt: skip
    log = open(tmp_path / "lab.log", "wb")  # noqa: SIM115
    server = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
        deadline = time.monotonic() + 90.0
        while True:
            if server.poll() is not None:
                pytest.fail(f"jupyter lab exited: {(tmp_path / 'lab.log').read_text()[-2000:]}")
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail("jupyter lab did not start within 90 s")
                time.sleep(0.2)
        yield f"http://127.0.0.1:{port}/lab/tree/explorer.ipynb?token={TOKEN}"
    finally:
        server.terminate()
        try:
            server.wait(15)
        except subprocess.TimeoutExpired:
            server.kill()
        log.close()


def _screenshot(locator, tmp_path, name):
    locator.screenshot(path=str(tmp_path / name))
    folder = os.environ.get("JAXLENS_SCREENSHOTS")
    if folder:
        shutil.copy(tmp_path / name, Path(folder) / name)


def _set_readout(page, label, value):
    """Type a value into a slider's readout, as a user does (Enter commits it)."""
    readout = page.locator(".widget-slider", has_text=label).locator(".widget-readout")
    readout.click()
    page.keyboard.press("Control+A")
    page.keyboard.type(str(value))
    page.keyboard.press("Enter")


def test_explorer_in_jupyterlab(lab, tmp_path):
    with sync_api.sync_playwright() as p:
        chromium = _chromium(p)
        if chromium is None:
            pytest.skip("no Chromium to drive: run `python -m playwright install chromium` or "
                        "install the system's (apt-get install chromium), or set "
                        "JAXLENS_CHROMIUM to its path")  # fmt: skip
        browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(lab)
            page.wait_for_function(
                "() => { const w = window.jupyterapp && window.jupyterapp.shell.currentWidget;"
                " return w && w.sessionContext && w.sessionContext.session"
                " && w.sessionContext.session.kernel; }",
                timeout=120_000,
            )
            page.evaluate("window.jupyterapp.commands.execute('notebook:run-all-cells')")
            img = page.locator(".widget-image")
            page.wait_for_function(
                "() => { const i = document.querySelector('.widget-image');"
                " return i && i.naturalWidth > 0; }",
                timeout=180_000,
            )
            natural = page.evaluate(
                "() => { const i = document.querySelector('.widget-image');"
                " return [i.naturalWidth, i.naturalHeight]; }"
            )
            box = img.bounding_box()
            assert natural == [240, 135]
            # Shown 320 wide at the render's aspect ratio, not stretched to the sliders.
            assert box["width"] == pytest.approx(320, abs=1)
            assert box["height"] == pytest.approx(320 * 135 / 240, abs=1)
            output = page.locator(".jp-OutputArea-output").first
            _screenshot(output, tmp_path, "explorer.png")

            status = page.locator(".widget-label", has_text="240x135")
            for label, value in (("distance (R_S)", 8), ("star lon (deg)", 4)):
                src = img.get_attribute("src")
                _set_readout(page, label, value)
                page.wait_for_function(
                    "s => document.querySelector('.widget-image').src !== s", arg=src,
                    timeout=120_000,
                )  # fmt: skip
                assert img.bounding_box() == box
            assert status.count() == 1

            # A new sky compiles a new program for seconds: the status says so meanwhile.
            src = img.get_attribute("src")
            page.locator(".widget-dropdown select").select_option("checker")
            page.wait_for_function(
                "() => [...document.querySelectorAll('.widget-label')]"
                ".some(e => e.textContent === 'rendering...')",
                timeout=30_000,
            )
            page.wait_for_function(
                "s => document.querySelector('.widget-image').src !== s", arg=src,
                timeout=180_000,
            )  # fmt: skip
            page.locator(".widget-label", has_text="240x135").wait_for(timeout=30_000)
            assert img.bounding_box() == box
            _screenshot(output, tmp_path, "explorer_checker.png")
        finally:
            browser.close()
