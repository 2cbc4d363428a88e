"""The API reference reads well: it renders each package's public names (docs/griffe_public.py), no
Sphinx role is left as raw text, every role resolves, and every public module constant has a
description (docs/griffe_roles.py); both are the docs build's griffe extensions.

The fast checks load the package with griffe and the extensions as the docs build does (no mkdocs
needed). The last one builds the site (``mkdocs build --strict``, a few seconds; skipped without
mkdocs) and looks for raw roles in the HTML itself.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

griffe = pytest.importorskip("griffe")

REPO = Path(__file__).resolve().parents[1]


def _extension_module(name):
    spec = importlib.util.spec_from_file_location(name, REPO / "docs" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


roles = _extension_module("griffe_roles")
public = _extension_module("griffe_public")


def load(*extensions):
    return griffe.load(
        "jaxloc",
        search_paths=[str(REPO)],
        extensions=griffe.load_extensions(*extensions),
        docstring_parser="google",
        resolve_aliases=False,
    )


@pytest.fixture(scope="module")
def loaded():
    extension = roles.SphinxRoles()
    return load(public.PublicNames(), extension), extension


PACKAGES = [
    "jaxloc",
    "jaxloc.io",
    "jaxloc.m2loc",
    "jaxloc.sg2loc",
    "jaxloc.sg2loc.learn",
    "jaxloc.sg2loc.refine",
    "jaxloc.mapping",
    "jaxloc.raycasting",
    "jaxloc.synthetic.indoor",
]


def exports(root, package) -> list[str]:
    module = root if package == "jaxloc" else root[package.removeprefix("jaxloc.")]
    return [str(name) for name in module.exports or []]


@pytest.mark.parametrize("package", PACKAGES)
def test_the_reference_exports_what_the_package_exports(loaded, package):
    """``__all__`` is derived at run time, which griffe cannot read: with the extension, griffe's
    exports are ``__all__``, in its order."""
    assert exports(loaded[0], package) == importlib.import_module(package).__all__


def test_without_the_extension_the_reference_misses_names():
    bare = load()
    assert all(
        exports(bare, package) != importlib.import_module(package).__all__ for package in PACKAGES
    )


def raw_roles(package) -> dict[str, list[str]]:
    found = {}
    for obj in roles.walk(package):
        if obj.docstring is not None and (hits := roles.RAW_ROLE.findall(obj.docstring.value)):
            found[obj.path] = hits
    return found


def test_no_docstring_keeps_a_raw_role(loaded):
    package, extension = loaded
    assert raw_roles(package) == {}
    assert len(extension.links) > 400  # the roles of the sources became links


def test_the_check_sees_raw_roles():
    """Without the extension the same check finds the roles (so it is not vacuous), in package
    docstrings too (the first thing the extension missed: its pattern lacked the role's colon)."""
    found = raw_roles(load())
    assert len(found) > 100 and "jaxloc.m2loc" in found


def test_every_role_resolves(loaded):
    """A role that is not a link is inline code for a reason: its target is a private jaxloc
    object (no page renders it) or lies outside jaxloc in an importable package (jax, numpy);
    a typo or a stale name fails here."""
    _, extension = loaded
    assert extension.links and all(link in extension.rendered for _, _, link in extension.links)
    wrong = []
    for where, target, found in extension.code:
        if found is not None:
            ok = any(part.startswith("_") for part in found.split("."))
        else:
            root = target.split(".")[0]
            ok = root != "jaxloc" and "." in target and importlib.util.find_spec(root) is not None
        if not ok:
            wrong.append(f"{where}: {target}")
    assert not wrong, "roles that name nothing rendered:\n" + "\n".join(wrong)


def test_rendered_objects_follow_the_pages(loaded):
    """The extension's idea of what is rendered: re-exports are followed to their objects, private
    helpers and ``members: false`` packages' own members are not."""
    _, extension = loaded
    rendered = extension.rendered
    assert "jaxloc.m2loc._clusters.cluster_instances" in rendered  # as jaxloc.m2loc's
    assert "jaxloc.sg2loc._localization.localize" in rendered
    assert "jaxloc.raycasting.traversal._wide_nodes" not in rendered
    assert "jaxloc.sg2loc._EXPORTS" not in rendered


def test_every_public_constant_has_a_description(loaded):
    """Each module attribute that the API pages render, and each UPPER_CASE name of a public
    module, has a docstring or a ``#:`` comment right above it (which the extension makes its
    docstring)."""
    package, extension = loaded
    missing = []
    for obj in roles.walk(package):
        if not (obj.is_attribute and obj.parent.is_module):
            continue
        public_module = not any(p.startswith("_") for p in obj.parent.path.split("."))
        constant = public_module and obj.name.isupper() and not obj.name.startswith("_")
        if (obj.path in extension.rendered or constant) and not (
            obj.docstring and obj.docstring.value.strip()
        ):
            missing.append(obj.path)
    assert missing == [], "constants without a description"
    assert "jaxloc.scene.MIN_TRIANGLE_AREA" not in missing  # a ``#:`` comment counts


def test_comment_blocks():
    lines = ["X = 1", "", "#: First line", "#:second", "Y = 2", "# plain", "Z = 3"]
    assert roles.comment_block(lines, 5) == (3, ["First line", "second"])
    assert roles.comment_block(lines, 7) is None
    assert roles.comment_block(lines, 1) is None


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None, reason="mkdocs not installed")
def test_the_site_shows_no_raw_role(tmp_path):
    """``mkdocs build --strict`` (every link resolves) and no role left in the API pages' HTML."""
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    build = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(site)],
        cwd=REPO / "docs",
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert build.returncode == 0, build.stdout + build.stderr
    role = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|obj|exc|const):")
    pages = sorted((site / "api").glob("*/index.html"))
    assert pages
    left = {p.parent.name: n for p in pages if (n := len(role.findall(p.read_text())))}
    assert left == {}
