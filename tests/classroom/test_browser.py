"""The explorers in a real browser: JupyterLab and Notebook 7 in headless Chromium.

Each test starts a Jupyter server on a free port of 127.0.0.1 (a random token, a temporary
root) with a notebook that shows explorers, opens it in the system's Chromium through
Playwright, runs every cell and then uses the page as a keyboard user would: focus each
slider, press the arrow keys, and check that the slider moved, kept the focus (the notebook's
shortcuts did not take the key: ArrowDown would select the next cell) and that the kernel
received the value (the explorer redrew: its picture's alt text changed). Every explorer
picture must carry an alt text.

Marked ``browser``; run them with ``python -m pytest -m browser tests/classroom/test_browser.py``.
They need ``chromium`` on PATH (Debian: ``apt-get install chromium``; ``.ci/run`` installs it)
and the Python package ``playwright`` (no browser download: the system Chromium is used).
Without Chromium they are skipped, except under CI (``CI`` set), where that is a failure.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import secrets
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import nbformat
import pytest

pytestmark = pytest.mark.browser

ROOT = Path(__file__).resolve().parents[2]

#: The notebook: explorers whose sliders are driven (one MPC explorer, one rule, the picker).
CELLS = [
    "from mpcrl_lite.classroom import widgets",
    "widgets.price_day_picker()",
    "widgets.rule_explorer()",
    "widgets.day_explorer()",
]
#: Sliders per explorer, in page order: picker 3, rule 6, day 6 (the seed is a number box).
SLIDERS = 3 + 6 + 6


def _chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None or importlib.util.find_spec("playwright") is None:
        missing = "chromium on PATH" if path is None else "the playwright package"
        if os.environ.get("CI"):
            pytest.fail(f"browser test: {missing} is needed (apt-get install chromium; "
                        "pip install playwright)")
        pytest.skip(f"needs {missing} (apt-get install chromium; pip install playwright)")
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _server(app: str, root: Path) -> Iterator[tuple[str, str]]:
    """A Jupyter server (``app`` = ``lab`` or ``notebook``) on ``root``; yields its base URL
    and its token."""
    token, port = secrets.token_hex(16), _free_port()
    jupyter = Path(sys.executable).with_name("jupyter")
    expose = ("--LabApp.expose_app_in_browser=True" if app == "lab"
              else "--JupyterNotebookApp.expose_app_in_browser=True")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    log = open(root / f"{app}.log", "w")  # noqa: SIM115 - closed below
    process = subprocess.Popen(
        [str(jupyter), app, "--no-browser", f"--port={port}", "--ip=127.0.0.1",
         f"--IdentityProvider.token={token}", expose, "--allow-root",
         f"--ServerApp.root_dir={root}"],
        cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                urllib.request.urlopen(f"{base}/api/status?token={token}", timeout=2)
                break
            except OSError:
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"jupyter {app} did not start: "
                                       + (root / f"{app}.log").read_text()[-2000:]) from None
                time.sleep(0.5)
        yield base, token
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
        log.close()


_KERNEL_IDLE = """() => {
  const app = window.jupyterapp; if (!app) return false;
  const panel = [...app.shell.widgets('main')].find(w => w.sessionContext);
  if (!panel) return false;
  app.shell.activateById(panel.id);
  const kernel = panel.sessionContext.session?.kernel;
  return !!kernel && kernel.status === 'idle';
}"""

_READY = """(count) => {
  const sliders = document.querySelectorAll('.mpcrl-step-slider input[type=range]');
  const pictures = [...document.querySelectorAll('img.mpcrl-picture')].filter(i => i.src);
  return sliders.length >= count && pictures.length >= 3;
}"""


def _drive(url: str, chromium: str, tmp: Path) -> dict:
    """Open ``url``, run every cell and press keys on every slider; returns what was seen."""
    from playwright.sync_api import sync_playwright

    seen: dict = {"moves": [], "pictures": []}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium,
                                    args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 1000})
            page.goto(url)
            page.wait_for_function(_KERNEL_IDLE, timeout=120_000)
            page.evaluate("() => window.jupyterapp.commands.execute('notebook:run-all-cells')")
            page.wait_for_function(_READY, arg=SLIDERS, timeout=240_000, polling=1000)
            sliders = page.locator(".mpcrl-step-slider input[type=range]")
            for i in range(sliders.count()):
                slider = sliders.nth(i)
                slider.scroll_into_view_if_needed()
                slider.focus()
                name = slider.get_attribute("aria-label")
                start = int(slider.input_value())
                top = int(slider.get_attribute("max"))
                up, down = ("ArrowRight", "ArrowLeft") if start < top else ("ArrowLeft",
                                                                            "ArrowRight")
                step = 1 if start < top else -1
                record = {"name": name, "start": start}
                for key, expected in ((up, start + step), (down, start),
                                      ("ArrowUp" if step > 0 else "ArrowDown", start + step),
                                      ("ArrowDown" if step > 0 else "ArrowUp", start)):
                    page.keyboard.press(key)
                    record[key] = (int(slider.input_value()), expected,
                                   slider.evaluate("el => el === document.activeElement"))
                seen["moves"].append(record)
            # the kernel receives a key's value: the picker's picture changes its alt text
            picture = page.locator("img.mpcrl-picture").first
            before = picture.get_attribute("alt")
            day = sliders.first
            day.focus()
            page.keyboard.press("End")
            page.wait_for_function(
                "([img, old]) => img.alt !== old", arg=[picture.element_handle(), before],
                timeout=60_000)
            seen["alt_after_key"] = (before, picture.get_attribute("alt"))
            seen["pictures"] = page.eval_on_selector_all(
                ".jp-OutputArea img", "imgs => imgs.map(i => i.getAttribute('alt'))")
            page.screenshot(path=str(tmp / "page.png"), full_page=True)
        finally:
            browser.close()
    return seen


@pytest.fixture(scope="module")
def notebook_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("browser")
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell(source) for source in CELLS]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}
    nbformat.write(nb, root / "check.ipynb")
    return root


def _check(seen: dict) -> None:
    assert len(seen["moves"]) == SLIDERS
    for record in seen["moves"]:
        for key, value in record.items():
            if key.startswith("Arrow"):
                got, expected, focused = value
                assert got == expected, f"{record['name']}: {key} gave {got}, expected {expected}"
                assert focused, f"{record['name']}: {key} took the focus off the slider"
    before, after = seen["alt_after_key"]
    assert before and after and before != after
    assert seen["pictures"] and all(alt and alt.startswith("Figure") for alt in seen["pictures"])


def test_arrow_keys_move_every_slider_in_jupyterlab(notebook_dir):
    chromium = _chromium()
    with _server("lab", notebook_dir) as (base, token):
        seen = _drive(f"{base}/lab/tree/check.ipynb?token={token}", chromium, notebook_dir)
    _check(seen)


def test_arrow_keys_move_every_slider_in_notebook(notebook_dir):
    chromium = _chromium()
    if importlib.util.find_spec("notebook") is None:
        if os.environ.get("CI"):
            pytest.fail("the notebook package (Notebook 7) is in environment-requirements.txt")
        pytest.skip("needs the notebook package (Notebook 7)")
    with _server("notebook", notebook_dir) as (base, token):
        seen = _drive(f"{base}/notebooks/check.ipynb?token={token}", chromium, notebook_dir)
    _check(seen)
