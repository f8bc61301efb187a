"""Sphinx configuration of the scatmodes documentation (``make docs``).

The site is built offline with warnings as errors: no intersphinx, MathJax served from the
copy that the ``jupyter-server-mathjax`` package ships, the theme's own bundled fonts. The API
pages are generated from the packages' ``__all__`` (:func:`_write_api_pages`), so a public
name cannot be missing from them; the notebooks in ``notebooks/`` are executed at reduced
size, as the test suite runs them.
"""

from __future__ import annotations

import importlib
import inspect
import os
import re
import shutil
import sys
import types
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import Directive

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))

import basis  # noqa: E402

project = "scatmodes"
author = "the scatmodes developers"
copyright = "2026, the scatmodes developers"
release = version = basis.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "myst_nb",
]

templates_path = ["_templates"]
exclude_patterns = ["_build", "**.ipynb_checkpoints"]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
root_doc = "index"
nitpicky = False

# -- API pages --------------------------------------------------------------------------------

#: the documented namespaces, each a page of the API reference that opens with the module's
#: docstring: (module, title)
API = [
    ("basis", "basis: bases, quadrature, coefficient matrices"),
    ("project", "project: BRDFs, projection and fits"),
    ("project.models", "project.models: analytic BRDF models"),
    ("project.measured", "project.measured: measured data"),
    ("project.microgeometry", "project.microgeometry: the Monte Carlo simulator"),
    ("compress", "compress: compression, storage, studies"),
    ("compress.mitsuba", "compress.mitsuba: the Mitsuba 3 plugin"),
]


def _public(module: str) -> tuple[list[str], list[str]]:
    """Return the names of a module's ``__all__``: (classes and functions, data), in order."""
    mod = importlib.import_module(module)
    objects, data = [], []
    for name in mod.__all__:
        obj = getattr(mod, name)
        if isinstance(obj, types.ModuleType):
            continue  # a subpackage: a page of its own
        (objects if inspect.isclass(obj) or callable(obj) else data).append(name)
    return objects, data


def _comment(module: str, name: str) -> str:
    """Return the ``#:`` comment of a constant where it is defined (any of our modules)."""
    from sphinx.pycode import ModuleAnalyzer

    mod = importlib.import_module(module)
    candidates = [module] + sorted(m for m in list(sys.modules)
                                   if m.split(".")[0] in ("basis", "project", "compress"))
    for source in candidates:
        try:
            docs = ModuleAnalyzer.for_module(source).find_attr_docs()
        except Exception:  # noqa: BLE001 (compiled or source-less modules)
            continue
        if ("", name) in docs and getattr(sys.modules[source], name, None) is getattr(mod, name):
            return " ".join(line.strip() for line in docs[("", name)] if line.strip())
    raise RuntimeError(f"{module}.{name} is public but has no #: comment to document it")


def _write_api_pages() -> None:
    """Write ``api/*.rst`` from the packages' ``__all__`` (generated files, not committed)."""
    out = DOCS / "api"
    out.mkdir(exist_ok=True)
    index = ["API reference", "=============", "",
             "Every public name of ``basis``, ``project`` and ``compress``: the names in each "
             "package's ``__all__``.", "", ".. toctree::", "   :maxdepth: 1", ""]
    for module, title in API:
        objects, data = _public(module)
        lines = [title, "=" * len(title), "", f".. automodule:: {module}", "   :no-members:",
                 "", f".. currentmodule:: {module}", ""]
        if objects:
            lines += ["Classes and functions", "---------------------", "",
                      ".. autosummary::", "   :toctree: generated", "   :nosignatures:", ""]
            lines += [f"   {name}" for name in objects] + [""]
        if data:
            lines += ["Constants", "---------", ""]
            for name in data:
                value = repr(getattr(importlib.import_module(module), name))
                if len(value) > 90:
                    value = value[:87] + "..."
                lines += [f".. data:: {name}", f"   :value: {value}", "",
                          f"   {_comment(module, name)}", ""]
        text = "\n".join(lines)
        page = out / f"{module}.rst"
        if not page.is_file() or page.read_text() != text:
            page.write_text(text)
        index.append(f"   {module}")
    (out / "index.rst").write_text("\n".join(index) + "\n")


_write_api_pages()

autosummary_generate = True
autosummary_imported_members = True
autodoc_default_options = {"members": False}
autodoc_typehints = "none"  # numpydoc's Parameters sections give the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# -- notebooks --------------------------------------------------------------------------------

# the sizes the test suite runs them at (tests/test_notebooks.py); the kernel inherits these
for _key, _val in {"SCATMODES_NB_SMALL": "1", "SCATMODES_NB_RAYS": "4000",
                   "SCATMODES_NB_RESOLUTION": "64", "MPLBACKEND": "Agg",
                   "JUPYTER_PLATFORM_DIRS": "1", "PYDEVD_DISABLE_FILE_VALIDATION": "1"}.items():
    os.environ.setdefault(_key, _val)
nb_execution_mode = os.environ.get("SCATMODES_DOCS_EXECUTE", "force")
nb_execution_in_temp = True
nb_execution_timeout = 300
nb_execution_raise_on_error = True
nb_merge_streams = True
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

# -- HTML -------------------------------------------------------------------------------------

html_theme = "pydata_sphinx_theme"
html_title = f"scatmodes {release}"
html_static_path: list[str] = []
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "header_links_before_dropdown": 7,
}
# light or dark as the reader's system prefers (an empty mode logs a console error)
html_context = {"default_mode": "auto"}
# MathJax 2 from the jupyter-server-mathjax package: the site loads no remote script
mathjax_path = "mathjax/MathJax.js?config=TeX-AMS-MML_HTMLorMML-full"
mathjax2_config = {"tex2jax": {"inlineMath": [["\\(", "\\)"]],
                               "displayMath": [["\\[", "\\]"]],
                               "processEscapes": True,
                               "ignoreClass": "document",
                               "processClass": "math|output_area"}}


def _copy_mathjax(app, exception) -> None:  # noqa: ANN001
    if exception is not None or app.builder.format != "html":
        return
    import jupyter_server_mathjax
    source = Path(jupyter_server_mathjax.__file__).parent / "static"
    shutil.copytree(source, Path(app.outdir) / "_static" / "mathjax", dirs_exist_ok=True)


_CODE = re.compile(r"(``.*?``|`[^`]*`)")


def _plain_pipes(app, what, name, obj, options, lines) -> None:  # noqa: ANN001
    """Escape ``|`` outside code in docstrings.

    The docstrings write absolute values and norms as plain text (``|m|``, ``|wi + wo|``),
    which reStructuredText would read as substitution references; they hold no substitutions,
    line blocks or grid tables.
    """
    for i, line in enumerate(lines):
        if "|" in line:
            parts = _CODE.split(line)
            lines[i] = "".join(part if k % 2 else part.replace("|", "\\|")
                               for k, part in enumerate(parts))


class CommandHelp(Directive):
    """``.. command-help::``: each ``scatmodes`` command's ``--help``, as the terminal shows it.

    The help texts are written for the terminal (argparse's raw description formatter), so
    they are shown as literal blocks, one section per command, rather than read as markup.
    """

    def run(self) -> list[nodes.Node]:
        """Return one section per command: its name and its help text."""
        import argparse

        from compress.cli.commands import _parser

        os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal's width
        parser = _parser()
        sections = [(parser.prog, parser)]
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                sections += [(sub.prog, sub) for sub in dict.fromkeys(action.choices.values())]
        out = []
        for prog, sub in sections:
            section = nodes.section(ids=[nodes.make_id(prog)])
            section += nodes.title(text=prog)
            help_text = sub.format_help()
            section += nodes.literal_block(help_text, help_text, language="text")
            out.append(section)
        return out


def setup(app) -> None:  # noqa: ANN001
    """Register the directive and the event handlers of this configuration."""
    app.add_directive("command-help", CommandHelp)
    app.connect("autodoc-process-docstring", _plain_pipes)
    app.connect("build-finished", _copy_mathjax)
