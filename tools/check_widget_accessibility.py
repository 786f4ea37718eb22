#!/usr/bin/env python
"""Render the explorers of ``mpcrl_lite.classroom.widgets`` in JupyterLab and check them as a browser does.

Starts a JupyterLab server on 127.0.0.1 (random free port, random token) in a temporary
directory, opens a notebook that displays every explorer in headless Chromium, runs it, and
reads the rendered page through the Chrome DevTools protocol:

* the accessible name of every focusable control, as Chromium computes it for screen readers
  (``Accessibility.queryAXTree``); a slider announced as "slider 18" has none;
* ``title="null"`` attributes (a "null" tooltip on hover);
* every explorer image: its pixel width against the width it is shown at (an image shown
  wider than it was drawn is blurry).

Usage::

    PYTHONPATH=$PWD python tools/check_widget_accessibility.py [--screenshot out.png]

Needs ``chromium`` (``apt-get install chromium``) and the notebook extras (JupyterLab,
ipywidgets, anywidget). Prints a report and exits with status 1 if a control has no name, a
``title="null"`` is found or an image is stretched.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import nbformat
import websocket

ROOT = Path(__file__).resolve().parent.parent

#: The notebook rendered: every explorer with its defaults (a short month for the LSTD one).
CELLS = [
    "from mpcrl_lite import widgets",
    "widgets.price_day_picker()",
    "widgets.rule_explorer()",
    "widgets.day_explorer()",
    "widgets.tau_explorer(points=11)",
    (
        "import numpy as np\n"
        "from mpcrl_lite.sim.closed_loop import run_month\n"
        "from mpcrl_lite.config import SystemConfig\n"
        "from mpcrl_lite.classroom.explorers import cached_solver\n"
        "from mpcrl_lite.system.prices import Prices\n"
        "from mpcrl_lite.theta import Theta\n"
        "system = SystemConfig()\n"
        "record = run_month(Theta.nominal(system), cached_solver(system), Prices.month(system, 3),\n"
        "                   system, np.random.default_rng(0), sensitivities=False)\n"
        "widgets.lstd_explorer(record)"
    ),
]
#: Roles of the controls a keyboard or screen-reader user operates.
CONTROL_ROLES = {"slider", "combobox", "spinbutton", "textbox", "button", "checkbox", "listbox",
                 "radio", "switch", "menulistpopup"}

_PAGE_STATE = """
(() => {
  const images = [...document.querySelectorAll('.jp-OutputArea img')].map(img => ({
    natural: img.naturalWidth, shown: img.getBoundingClientRect().width,
    ratio: window.devicePixelRatio}));
  const nulls = [...document.querySelectorAll('[title="null"]')].map(e => e.outerHTML.slice(0, 120));
  const sliders = document.querySelectorAll('.jp-OutputArea input[type=range]').length;
  const busy = document.querySelectorAll('.jp-OutputArea-promptOverlay, .jp-mod-busy').length;
  const done = [...document.querySelectorAll('.jp-InputArea-prompt')]
      .filter(e => /\\[\\d+\\]/.test(e.textContent)).length;
  return JSON.stringify({images, nulls, sliders, done});
})()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(predicate, timeout: float, what: str, step: float = 0.5):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")


class DevTools:
    """A minimal Chrome DevTools protocol client over one page's websocket."""

    def __init__(self, url: str) -> None:
        self.ws = websocket.create_connection(url, timeout=120)
        self.next_id = 0

    def call(self, method: str, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv())
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def evaluate(self, expression: str, await_promise: bool = False):
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                           awaitPromise=await_promise)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression[:80]}: {result['exceptionDetails']}")
        return result["result"].get("value")


def _unnamed_controls(tools: DevTools) -> tuple[list[dict], list[str]]:
    """Every control in the notebook's output areas with its computed accessible name."""
    root = tools.call("DOM.getDocument", depth=0)["root"]["nodeId"]
    areas = tools.call("DOM.querySelectorAll", nodeId=root,
                       selector=".jp-OutputArea-output")["nodeIds"]
    controls, unnamed = [], []
    for area in areas:
        for role in sorted(CONTROL_ROLES):
            for node in tools.call("Accessibility.queryAXTree", nodeId=area, role=role)["nodes"]:
                if node.get("ignored"):
                    continue
                name = (node.get("name") or {}).get("value", "")
                value = (node.get("value") or {}).get("value", "")
                controls.append({"role": role, "name": name, "value": value})
                if not str(name).strip():
                    unnamed.append(f"{role} (value {value!r})")
    return controls, unnamed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--screenshot", type=Path, help="write a PNG of the rendered page")
    parser.add_argument("--timeout", type=float, default=300.0)
    args = parser.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        parser.error("chromium not found: expected it on PATH (apt-get install chromium)")
    jupyter = Path(sys.executable).with_name("jupyter")
    token, port, debug_port = secrets.token_hex(16), _free_port(), _free_port()
    processes: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory() as tmp:
        nb = nbformat.v4.new_notebook()
        nb.cells = [nbformat.v4.new_code_cell(source) for source in CELLS]
        nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                     "language": "python"}
        nbformat.write(nb, Path(tmp) / "check.ipynb")
        env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
        try:
            processes.append(subprocess.Popen(
                [str(jupyter), "lab", "--no-browser", f"--port={port}", "--ip=127.0.0.1",
                 f"--IdentityProvider.token={token}", "--LabApp.expose_app_in_browser=True", "--allow-root",
                 f"--ServerApp.root_dir={tmp}"],
                cwd=tmp, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            base = f"http://127.0.0.1:{port}"

            def server_up() -> bool:
                try:
                    urllib.request.urlopen(f"{base}/api/status?token={token}", timeout=2)
                    return True
                except OSError:
                    return False

            _wait(server_up, 60, "the JupyterLab server")
            profile = Path(tmp) / "chromium-profile"
            processes.append(subprocess.Popen(
                [chromium, "--headless=new", "--no-sandbox", "--disable-gpu",
                 f"--remote-debugging-port={debug_port}", f"--user-data-dir={profile}",
                 "--window-size=1280,4000", "about:blank"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

            def page_socket() -> str | None:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{debug_port}/json",
                                                timeout=2) as r:
                        pages = [p for p in json.load(r) if p.get("type") == "page"]
                    return pages[0]["webSocketDebuggerUrl"] if pages else None
                except OSError:
                    return None

            tools = DevTools(_wait(page_socket, 60, "headless Chromium"))
            tools.call("Page.enable")
            tools.call("Accessibility.enable")
            tools.call("DOM.enable")
            tools.call("Page.navigate", url=f"{base}/lab/tree/check.ipynb?token={token}")
            # a headless page has no focus: activate the notebook so that commands act on it
            _wait(lambda: tools.evaluate(
                "(() => { const app = window.jupyterapp; if (!app) return false;"
                " const panel = [...app.shell.widgets('main')].find(w => w.sessionContext);"
                " if (!panel) return false; app.shell.activateById(panel.id);"
                " const kernel = panel.sessionContext.session?.kernel;"
                " return !!kernel && kernel.status === 'idle'; })()"), 120, "the kernel")
            tools.evaluate("window.jupyterapp.commands.execute('notebook:run-all-cells')",
                           await_promise=True)
            cells = len(CELLS)

            def finished():
                state = json.loads(tools.evaluate(_PAGE_STATE))
                return state if state["done"] >= cells and len(state["images"]) >= 5 else None

            state = _wait(finished, args.timeout, "every cell and explorer image", step=2.0)
            time.sleep(2.0)  # let the last widget views settle
            state = json.loads(tools.evaluate(_PAGE_STATE))
            controls, unnamed = _unnamed_controls(tools)
            if args.screenshot:
                shot = tools.call("Page.captureScreenshot", format="png",
                                  captureBeyondViewport=True)
                args.screenshot.write_bytes(base64.b64decode(shot["data"]))
        finally:
            for process in reversed(processes):
                process.terminate()
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
    slider_names = sorted({c["name"] for c in controls if c["role"] == "slider"})
    print(f"controls: {len(controls)} ({sum(c['role'] == 'slider' for c in controls)} sliders); "
          f"without an accessible name: {len(unnamed)}")
    for item in unnamed[:20]:
        print(f"  unnamed: {item}")
    print(f"slider names: {slider_names}")
    print(f'title="null" attributes: {len(state["nulls"])}')
    for html in state["nulls"][:5]:
        print(f"  {html}")
    stretched = [im for im in state["images"] if im["shown"] * im["ratio"] > im["natural"] + 1]
    for im in state["images"]:
        print(f"image: {im['natural']} px drawn, shown at {im['shown']:.0f} CSS px "
              f"(device pixel ratio {im['ratio']:g})")
    print(f"stretched images: {len(stretched)}")
    return int(bool(unnamed or state["nulls"] or stretched))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
