"""Checks of the built documentation site, run by ``make docs`` after Sphinx.

``make docs`` builds ``docs/_build/html`` with warnings as errors and then runs this file with
``SCATMODES_DOCS_SITE`` set to that folder; without it (``make test``) these tests skip, since
the site has not been built. What is checked:

- every public name of ``basis``, ``project`` and ``compress`` (the ``__all__`` of each module
  the API reference documents) appears in the generated index, and the command-line page
  shows every ``scatmodes`` command;
- no page loads a remote script, style sheet, font or image (the site works offline);
- the front page, an API page and a notebook open in headless Chromium without console
  errors and without a request that leaves the machine.
"""

from __future__ import annotations

import html
import importlib
import os
import re
import types
from pathlib import Path

import pytest

SITE = os.environ.get("SCATMODES_DOCS_SITE")
pytestmark = pytest.mark.skipif(not SITE, reason="the site is built and checked by make docs")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site() -> Path:
    path = Path(SITE).resolve()
    if not (path / "index.html").is_file():
        pytest.fail(f"no built site at {path}: run `make docs`")
    return path


def _documented_modules() -> list[str]:
    """The modules of the API reference, read from docs/conf.py (the single list)."""
    text = (ROOT / "docs" / "conf.py").read_text(encoding="utf-8")
    block = text[text.index("API = ["):text.index("]\n", text.index("API = ["))]
    return re.findall(r'\("([a-z_.]+)", "', block)


def test_the_reference_covers_the_three_packages():
    modules = _documented_modules()
    assert {"basis", "project", "compress"} <= set(modules)
    for module in ("basis", "project", "compress"):
        subpackages = [name for name in importlib.import_module(module).__all__
                       if isinstance(getattr(importlib.import_module(module), name),
                                     types.ModuleType)]
        assert {f"{module}.{name}" for name in subpackages} <= set(modules)


def test_every_public_name_is_in_the_index(site):
    index = html.unescape((site / "genindex.html").read_text(encoding="utf-8"))
    missing = []
    for module in _documented_modules():
        mod = importlib.import_module(module)
        for name in mod.__all__:
            if isinstance(getattr(mod, name), types.ModuleType):
                continue
            # each entry of the index links to the object's anchor, "#module.name"
            if f'#{module}.{name}"' not in index:
                missing.append(f"{module}.{name}")
    assert missing == [], f"public names missing from genindex.html: {missing}"


def test_the_command_line_page_shows_every_command(site):
    import argparse

    from compress.cli.commands import _parser

    page = re.sub(r"<[^>]+>", "", (site / "cli.html").read_text(encoding="utf-8"))
    page = html.unescape(page)
    sub = next(a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction))
    for command in sub.choices:
        assert f"usage: scatmodes {command}" in page, command


REMOTE_TAG = re.compile(
    r"<(?:script|img|iframe|source|video|audio)\b[^>]*\bsrc=[\"'](?:https?:)?//"
    r"|<link\b(?=[^>]*\brel=[\"'](?:stylesheet|preload|icon|modulepreload|prefetch)"
    r"[\"' ])[^>]*\bhref=[\"'](?:https?:)?//", re.IGNORECASE)
REMOTE_CSS = re.compile(r"(?:url\(\s*[\"']?|@import\s+[\"'])(?:https?:)?//", re.IGNORECASE)


def test_nothing_is_loaded_from_elsewhere(site):
    bad = []
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8", errors="replace")
        bad += [f"{page.relative_to(site)}: {m.group(0)}" for m in REMOTE_TAG.finditer(text)]
    for sheet in site.rglob("*.css"):
        text = sheet.read_text(encoding="utf-8", errors="replace")
        bad += [f"{sheet.relative_to(site)}: {m.group(0)}" for m in REMOTE_CSS.finditer(text)]
    assert bad == []


def test_the_guides_and_results_are_pages(site):
    for page in ("bases", "projection", "fitting", "measured-data", "non-reciprocal",
                 "compression", "rendering", "reports", "microgeometry", "storage",
                 "scale-out", "conventions", "papers", "results/merl", "results/rgl",
                 "results/speed", "changelog"):
        assert (site / f"{page}.html").is_file(), page


@pytest.mark.parametrize("page", ["index.html", "api/generated/basis.HemiZernike.html",
                                  "notebooks/01_bases.html"])
def test_pages_open_in_a_browser_without_errors(site, browser, page):
    for domain in ("Page", "Runtime", "Log", "Network"):
        browser.page(f"{domain}.enable")
    browser.page("Page.navigate", url=(site / page).as_uri())
    browser.wait("Page.loadEventFired")
    title = browser.page("Runtime.evaluate", expression="document.title",
                         returnByValue=True)["result"]["value"]
    assert "scatmodes" in title
    requests = [e["params"]["request"]["url"] for e in browser.events
                if e.get("method") == "Network.requestWillBeSent"]
    assert requests and all(url.startswith(("file:", "data:", "about:")) for url in requests), \
        [u for u in requests if not u.startswith(("file:", "data:", "about:"))]
    assert browser.errors() == []
