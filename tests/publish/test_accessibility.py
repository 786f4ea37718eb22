"""The site's pages in a real browser: axe-core finds no accessibility violation, every page
has its own title, and every file a page asks for (MathJax's fonts included) is there.

Marked ``browser`` (and ``notebook``: the site is built by executing notebooks 01 and 02 with
the ci profile). Needs ``chromium`` on PATH, the Python package ``playwright`` and the npm
package ``axe-core`` (``npm install --no-save axe-core@4`` in the repository, as ``.ci/run``
does; or ``AXE_CORE_JS`` naming its ``axe.min.js``). Without them the test is skipped, except
under CI (``CI`` set), where that is a failure.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from mpcrl_lite.publish import site as site_module

pytestmark = [pytest.mark.browser, pytest.mark.notebook]

ROOT = Path(__file__).resolve().parents[2]
STEMS = ["01_battery_dynamics", "02_mpc_policy"]


def _need(what: str) -> None:
    if os.environ.get("CI"):
        pytest.fail(f"the accessibility test needs {what}")
    pytest.skip(f"needs {what}")


def _axe_source() -> str:
    candidates = [os.environ.get("AXE_CORE_JS", ""),
                  str(ROOT / "node_modules" / "axe-core" / "axe.min.js")]
    npm = shutil.which("npm")
    if npm:
        run = subprocess.run([npm, "root", "-g"], capture_output=True, text=True)
        if run.returncode == 0:
            candidates.append(str(Path(run.stdout.strip()) / "axe-core" / "axe.min.js"))
    for candidate in candidates:
        if candidate and Path(candidate).is_file():
            return Path(candidate).read_text(encoding="utf-8")
    _need("axe-core (npm install --no-save axe-core@4)")
    raise AssertionError  # unreachable


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("a11y") / "site"
    site_module.build_site(out, profile="ci", notebooks=STEMS)
    return out


def _audit(pages: list[Path]) -> dict[str, dict]:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None or importlib.util.find_spec("playwright") is None:
        _need("chromium on PATH and the playwright package")
    axe = _axe_source()
    from playwright.sync_api import sync_playwright

    seen: dict[str, dict] = {}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        try:
            for path in pages:
                page = browser.new_page()
                failed: list[str] = []
                page.on("requestfailed", lambda r, failed=failed: failed.append(r.url))
                page.goto(path.as_uri())
                # MathJax typesets after load; axe then sees the page a reader sees
                page.wait_for_function(
                    "() => !window.MathJax || (MathJax.Hub && MathJax.Hub.queue.pending === 0"
                    " && MathJax.Hub.queue.running === 0)", timeout=60_000)
                page.wait_for_timeout(500)
                page.add_script_tag(content=axe)
                result = page.evaluate(
                    "async () => await axe.run(document, {resultTypes: ['violations']})")
                seen[path.name] = {
                    "title": page.title(),
                    "failed": [u for u in failed if u.startswith("file:")],
                    "violations": {v["id"]: [n["target"] for n in v["nodes"][:5]]
                                   for v in result["violations"]},
                }
                page.close()
        finally:
            browser.close()
    return seen


def test_site_pages_pass_axe_with_titles_and_every_file(site):
    pages = [site / "index.html", *(site / "notebooks" / f"{s}.html" for s in STEMS)]
    seen = _audit(pages)
    titles = set()
    for name, found in seen.items():
        assert found["violations"] == {}, f"{name}: {found['violations']}"
        assert found["failed"] == [], f"{name}: missing files {found['failed']}"
        assert found["title"] and found["title"] != "Notebook", name
        titles.add(found["title"])
    assert len(titles) == len(pages)  # every page its own title
    assert seen["02_mpc_policy.html"]["title"] == "02 · The MPC policy · mpcrl_lite"
