"""Griffe extension of the docs build: Sphinx cross-reference roles in jaxloc's docstrings
(``:func:`~jaxloc.sg2loc.localize``` and the like) become mkdocs-autorefs links, and a ``#:``
comment block right above an attribute without a docstring becomes its docstring (as Sphinx
autodoc reads it).

A role's target is looked up as written when it starts with ``jaxloc.``, else relative to the
documented object's class, module and packages, as Sphinx does; an alias is followed to the object
it names. A target that the API pages render (``docs/pages/api/*.md``, with the handler's options:
public names only, imported names only when exported, no submodules, ``members: false`` honoured)
becomes a link to its canonical path, which mkdocstrings registers for every rendered object, also
when it is rendered under a re-exported name. Anything else becomes inline code: a jaxloc object
that no page renders (a private helper) and a name outside jaxloc (``jax.*``, ``numpy.*``).
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Any

import griffe

#: A Sphinx role: ``:func:`name```, ``:py:class:`~pkg.Name```, ``:meth:`title <Cls.name>```.
ROLE = re.compile(
    r":(?:py:)?(?:func|class|meth|mod|data|attr|obj|exc|const|type):"
    r"`(?:([^`<]*?)\s*<)?(~?)([A-Za-z_][\w.]*)(\(\))?>?`"
)
#: What is left of a role once the extension has run (the check of tests/test_docs_references.py).
RAW_ROLE = re.compile(r":(?:py:)?[a-z]+:\s*`")
#: The API pages whose ``:::`` lines decide what is rendered.
PAGES = Path(__file__).resolve().parent / "pages" / "api"

_ERRORS = (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError)


class SphinxRoles(griffe.Extension):
    """Rewrite the roles of every docstring of the package once it is loaded.

    After the load, ``rendered`` holds the canonical paths of the rendered objects, ``links``
    (documented object, role target, link target) the roles made links, ``code`` (documented
    object, role target, found) the roles made inline code, ``found`` the jaxloc object when
    there is one (not rendered), else None.
    """

    def __init__(self, pages: str | Path | None = None) -> None:
        super().__init__()
        self.pages = Path(pages) if pages else PAGES
        self.rendered: set[str] = set()
        self.links: list[tuple[str, str, str]] = []
        self.code: list[tuple[str, str, str | None]] = []

    def on_package(self, *, pkg: griffe.Module, loader: Any = None, **kwargs: Any) -> None:
        if pkg.path != "jaxloc":
            return
        objects = list(walk(pkg))
        for obj in objects:
            if obj.is_attribute and obj.docstring is None:
                _comment_docstring(obj, loader)
        self.rendered = rendered_paths(pkg, directives(self.pages))
        for obj in objects:
            if obj.docstring is not None:
                obj.docstring.value = ROLE.sub(
                    functools.partial(self._replace, pkg, obj), obj.docstring.value
                )
        for obj in objects:
            if obj.is_class and obj.docstring is not None:
                _attributes_once(obj)

    def _replace(self, root: griffe.Module, obj: griffe.Object, match: re.Match) -> str:
        title, tilde, target, call = match.group(1), match.group(2), match.group(3), match.group(4)
        text = title or (target.rsplit(".", 1)[-1] if tilde else target) + (call or "")
        found = resolve(root, obj, target)
        if found is not None and found.path in self.rendered:
            self.links.append((obj.path, target, found.path))
            return f"[`{text}`][{found.path}]"
        self.code.append((obj.path, target, found.path if found is not None else None))
        return f"`{text}`"


def walk(obj: griffe.Object):
    """``obj`` and every object defined under it (aliases are documented where they point)."""
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from walk(member)


def _lookup(root: griffe.Module, path: str) -> griffe.Object | griffe.Alias | None:
    if path == root.path:
        return root
    if not path.startswith(root.path + "."):
        return None
    try:
        return root[path[len(root.path) + 1 :]]
    except _ERRORS:
        return None


def _final(obj: griffe.Object | griffe.Alias) -> griffe.Object | None:
    try:
        return obj.final_target if obj.is_alias else obj
    except _ERRORS:
        return None  # an alias to a module outside jaxloc (jax, numpy)


def resolve(root: griffe.Module, obj: griffe.Object, target: str) -> griffe.Object | None:
    """The jaxloc object a role's ``target`` names in the docstring of ``obj``, as Sphinx looks it
    up: as written when absolute, else in the enclosing class, module and packages in turn."""
    candidates = [target] if target.startswith(root.path + ".") or target == root.path else []
    scope = obj if (obj.is_class or obj.is_module) else obj.parent
    while scope is not None:
        candidates.append(f"{scope.path}.{target}")
        scope = scope.parent
    for path in candidates:
        found = _lookup(root, path)
        if found is not None:
            found = _final(found)
            return found if found is not None and found.path.startswith(root.path) else None
    return None


def directives(pages: Path) -> list[tuple[str, bool]]:
    """The ``::: identifier`` lines of the API pages, with whether their members are rendered
    (not when the directive's options say ``members: false``)."""
    found: list[tuple[str, bool]] = []
    for page in sorted(pages.glob("*.md")):
        for line in page.read_text().splitlines():
            if line.startswith("::: "):
                found.append((line[4:].strip(), True))
            elif found and line.strip().replace(" ", "") == "members:false":
                found[-1] = (found[-1][0], False)
    return found


def rendered_paths(root: griffe.Module, pages: list[tuple[str, bool]]) -> set[str]:
    """Canonical paths of the objects that the ``:::`` directives render, with the handler's
    options of docs/mkdocs.yml: names matching ``^_`` filtered out, an imported name only when its
    module exports it, submodules only through their own directive, no inherited members."""
    seen: set[str] = set()
    expanded: set[str] = set()

    def visit(obj: griffe.Object | griffe.Alias, members: bool) -> None:
        target = _final(obj)
        if target is None:
            return
        seen.add(target.path)
        if not members or target.path in expanded:
            return
        expanded.add(target.path)
        for member in target.members.values():
            if member.name.startswith("_") or (member.is_alias and not member.is_public):
                continue
            final = _final(member)
            if final is not None and not final.is_module:
                visit(member, members=True)

    for identifier, members in pages:
        found = _lookup(root, identifier)
        if found is not None:
            visit(found, members)
    return seen


def comment_block(lines: list[str], lineno: int) -> tuple[int, list[str]] | None:
    """The ``#:`` comment lines right above line ``lineno`` (1-based) of ``lines``, without their
    ``#:`` marker, and the line number of the first; None when there are none."""
    block: list[str] = []
    index = lineno - 2
    while index >= 0 and lines[index].lstrip().startswith("#:"):
        text = lines[index].lstrip()[2:]
        block.insert(0, text[1:] if text.startswith(" ") else text)
        index -= 1
    return (index + 2, block) if block else None


def _entry_names(entry: griffe.DocstringAttribute) -> list[str]:
    """The attribute names of one ``Attributes:`` entry: ``fx, fy: ...`` parses as the name
    ``fx,`` with the annotation ``fy``."""
    if not entry.name.endswith(","):
        return [entry.name]
    return [entry.name[:-1], *(n.strip() for n in str(entry.annotation).split(","))]


def _attributes_once(cls: griffe.Object) -> None:
    """Move each ``Attributes:`` entry of the class docstring that names an attribute member onto
    that member (as its docstring, unless it has one), dropping the section once it is empty."""
    sections = cls.docstring.parsed
    for section in sections:
        if section.kind is not griffe.DocstringSectionKind.attributes:
            continue
        kept = []
        for entry in section.value:
            names = _entry_names(entry)
            members = [cls.members.get(name) for name in names]
            if not all(m is not None and not m.is_alias and m.is_attribute for m in members):
                kept.append(entry)
                continue
            for member in members:
                if member.docstring is None:
                    member.docstring = griffe.Docstring(entry.description, parent=member)
        section.value[:] = kept
    sections[:] = [
        s for s in sections if s.kind is not griffe.DocstringSectionKind.attributes or s.value
    ]


def _comment_docstring(attr: griffe.Object, loader: Any) -> None:
    if attr.lineno is None:
        return
    try:
        lines = attr.lines_collection[attr.filepath]
    except (KeyError, TypeError):
        return
    found = comment_block(lines, attr.lineno)
    if found is None:
        return
    first, block = found
    attr.docstring = griffe.Docstring(
        "\n".join(block).strip(),
        lineno=first,
        endlineno=first + len(block) - 1,
        parent=attr,
        parser=getattr(loader, "docstring_parser", None),
        parser_options=getattr(loader, "docstring_options", None),
    )
