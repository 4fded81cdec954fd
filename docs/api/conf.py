"""Sphinx configuration of echoloc's API reference (docs/api).

Build it with ``python3 dev.py docs``, or in any environment with ``echoloc[docs]``::

    sphinx-build -W --keep-going -b html docs/api docs/api/_build/html

The pages import the installed package (an editable install imports ``src/``). Nothing
is fetched at build time: no intersphinx, and the theme is Sphinx's built-in alabaster.

The lists of public names are not copied into the pages: ``public-names`` tables are
read from each package's ``__init__.pyi`` (the stubs lazy_loader reads), and the build
warns, so fails under ``-W``, when a public name has no entry in the reference or a
stable name (``echoloc.X``) is missing from, or a non-stable one documented on, the
stable page.
"""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path
from typing import Any, ClassVar

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.environment import BuildEnvironment
from sphinx.ext.autosummary import Autosummary
from sphinx.util import logging

import echoloc

project = "echoloc"
author = "the echoloc authors"
copyright = "the echoloc authors, MIT licence"
release = echoloc.__version__
version = release

extensions = ["sphinx.ext.autodoc", "sphinx.ext.autosummary", "sphinx.ext.viewcode"]

exclude_patterns = ["_build"]
# The docstrings write commands and options in single backticks (`echoloc stream`); the
# default role would set them in italics as titles.
default_role = "code"

# autodoc: the docstrings are reST as written (not numpydoc: no napoleon). Members in
# source order; a function's defaults as written (200e3, not 200000.0); types in the
# description, so that signatures stay readable.
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_preserve_defaults = True
autodoc_default_options = {"members": True}
autosummary_generate = False  # the tables link to the entries of the pages; no stub pages
add_module_names = False

html_theme = "alabaster"
html_title = f"echoloc {release} API reference"
html_theme_options = {
    "description": "Airborne ultrasonic echolocation for robots",
    "page_width": "1180px",
    "sidebar_width": "240px",
}
html_sidebars = {"**": ["about.html", "navigation.html", "searchbox.html"]}

PACKAGES = (
    "echoloc",
    "echoloc.physics",
    "echoloc.sim",
    "echoloc.tof",
    "echoloc.localise",
    "echoloc.maps",
    "echoloc.io",
    "echoloc.realtime",
    "echoloc.plots",
)
STABLE_PAGE = "stable"


def public_names(package: str) -> dict[str, str]:
    """A package's public names, from its ``__init__.pyi``, each with the full name of what
    it is (``Recording`` -> ``echoloc.io.recording.Recording``); subpackages left out."""
    spec = importlib.util.find_spec(package)
    if spec is None or spec.origin is None:
        raise ImportError(f"{package} is not installed")
    tree = ast.parse(Path(spec.origin).with_suffix(".pyi").read_text(encoding="utf-8"))
    names = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 1:
            for alias in node.names:
                names[alias.asname or alias.name] = f"{package}.{node.module}.{alias.name}"
    return dict(sorted(names.items()))


class PublicNames(Autosummary):
    """``.. public-names:: echoloc.tof``: a table of the package's public names, each with
    the first line of its docstring and a link to its entry."""

    required_arguments = 1
    optional_arguments = 0
    has_content = False
    option_spec: ClassVar[dict[str, Any]] = {}

    def run(self) -> list[nodes.Node]:
        package = self.arguments[0]
        self.arguments = []
        self.options = {"nosignatures": True}
        self.content = StringList([f"~{path}" for path in public_names(package).values()])
        # The entries are full names; inside the package's own page autosummary would ask
        # for them relative to the current module, so the table is made outside any.
        ref_context = self.env.ref_context
        current = ref_context.pop("py:module", None)
        try:
            return super().run()
        finally:
            if current is not None:
                ref_context["py:module"] = current


def check_public_names(app: Sphinx, env: BuildEnvironment) -> None:
    """Every public name has an entry; the stable page documents exactly the stable names."""
    logger = logging.getLogger(__name__)
    objects = env.get_domain("py").objects
    stable = set(public_names("echoloc").values())
    for package in PACKAGES:
        for name, path in public_names(package).items():
            if path not in objects:
                logger.warning(f"{package}.{name} ({path}) has no entry in the API reference")
            elif path in stable and objects[path].docname != STABLE_PAGE:
                logger.warning(f"stable name {path} is documented outside {STABLE_PAGE}.rst")
    for path, entry in objects.items():
        if entry.docname == STABLE_PAGE and path not in stable and "." in path.removeprefix("echoloc."):
            owner = path.rpartition(".")[0]
            if owner not in stable:  # a stable class's methods and attributes belong there
                logger.warning(f"{path} is on {STABLE_PAGE}.rst but is not a stable name")


def setup(app: Sphinx) -> None:
    app.add_directive("public-names", PublicNames)
    app.connect("env-check-consistency", check_public_names)
