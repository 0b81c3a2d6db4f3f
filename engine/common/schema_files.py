"""Schema files from several directories, and ``$ref`` resolved by file name whatever the ``$id``.

``--schemas`` may repeat: the directories are layered, a later one over the earlier (a user's
directory over the bundled one), and a file of a later directory replaces the file of the same
name (``position.v1.json``, ``vda5050/order.v2.json``) of an earlier one; every other file of
every directory is there too. So a user adds one schema, or replaces one, without copying the
bundled tree.

A ``$ref`` names a schema file, whatever the ``$id`` of the file holding it (a user's schema
has its own ``$id``, or none): before, ``$ref`` resolved against the ``$id`` only, so
``envelope.v1.json#/$defs/header`` in a schema whose ``$id`` was not
``https://rabbitros.dev/schemas/...`` did not resolve though the file was there. A reference
is looked up, in this order, as

1. the file of that relative name beside the referring file in the layered tree
   (``envelope.v1.json``; from a family, ``../envelope.v1.json``);
2. the ``$id`` some schema declares (``https://rabbitros.dev/schemas/envelope.v1.json``),
   the reference read against the referring schema's own ``$id``, as JSON Schema reads it;
3. the file of the reference's last name beside the referring file, then at the top
   (``https://example.com/any/where/envelope.v1.json``).

Each file is then given an ``$id`` of its own place in the tree (:data:`BASE` + its relative
name) and each ``$ref`` is rewritten to that absolute form (:func:`rewrite`), so the compiled
validators (jsonschema-rs, offline) and ``check``'s field walks follow exactly these rules.
"""

from __future__ import annotations

import posixpath
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import urldefrag, urljoin, urlsplit

FILE_NAME = re.compile(r"^(?P<name>[a-z][a-z0-9_]*)\.v(?P<version>\d+)\.json$")
FAMILY = re.compile(r"^[a-z][a-z0-9_]*$")
"""A subdirectory of schemas: one standard's family (``vda5050``), named as schema files are."""
BASE = "https://schema-files.rabbitros.invalid/"
"""The ``$id`` prefix each file is given, by its relative name (``.invalid``: never fetched)."""


@dataclass(frozen=True)
class SchemaFile:
    relative: str
    """Its name in the layered tree: ``position.v1.json``, ``vda5050/order.v2.json``."""
    path: Path
    replaces: tuple[Path, ...] = ()
    """The files of the same name in earlier directories, which this one replaces."""

    @property
    def uri(self) -> str:
        return BASE + self.relative


def layered(directories: Sequence[Path]) -> tuple[dict[str, SchemaFile], list[tuple[Path, str]]]:
    """Every schema file of ``directories`` (a later directory's file replacing an earlier's of
    the same name), and the problems: a directory that does not exist, a misnamed file."""
    files: dict[str, SchemaFile] = {}
    problems: list[tuple[Path, str]] = []
    for directory in directories:
        if not directory.is_dir():
            problems.append((directory, "schema directory does not exist"))
            continue
        for path in sorted(directory.glob("*.json")) + sorted(directory.glob("*/*.json")):
            if not FILE_NAME.match(path.name) or (path.parent != directory and not FAMILY.match(path.parent.name)):
                problems.append((path, "schema file names must look like name.v1.json"))
                continue
            relative = path.relative_to(directory).as_posix()
            earlier = files.get(relative)
            files[relative] = SchemaFile(relative, path, (*earlier.replaces, earlier.path) if earlier else ())
    return files, problems


@dataclass
class Resolver:
    """Finds the file a ``$ref`` names (module docstring's rules) among ``documents``."""

    documents: dict[str, Any]
    """Relative name -> the schema as read."""
    declared: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Every ``$id`` a schema declares (at its root or inside) -> (relative name, JSON pointer)."""

    def __post_init__(self) -> None:
        for relative, document in self.documents.items():
            for pointer, declared in _scopes(document, "", None):
                if declared is not None:
                    self.declared.setdefault(declared, (relative, pointer))

    def target(self, relative: str, base: str | None, reference: str) -> tuple[str, str] | None:
        """``(relative name, JSON pointer)`` of what ``reference`` names from the file
        ``relative`` (its ``$id`` scope ``base``), the fragment not included; None if nothing."""
        document_part, _ = urldefrag(reference)
        here = posixpath.dirname(relative)
        if not urlsplit(document_part).scheme and not document_part.startswith("/"):
            beside = posixpath.normpath(posixpath.join(here, document_part))
            if beside in self.documents:
                return beside, ""
        absolute = urldefrag(urljoin(base, document_part))[0] if base else document_part
        if absolute in self.declared:
            return self.declared[absolute]
        name = posixpath.basename(urlsplit(document_part).path)
        for candidate in (posixpath.join(here, name), name):
            if candidate in self.documents:
                return candidate, ""
        return None


def rewrite(relative: str, document: Any, resolver: Resolver) -> tuple[dict[str, Any], set[str], str | None]:
    """A copy of ``document`` whose ``$id`` is its place in the tree and whose every ``$ref``
    is absolute in that form; the files it refers to; the first reference that resolves to no
    file (None if all do)."""
    reached: set[str] = set()
    broken: list[str] = []

    def walk(node: Any, base: str | None, scope: str, pointer: str) -> Any:
        if isinstance(node, list):
            return [walk(item, base, scope, f"{pointer}/{index}") for index, item in enumerate(node)]
        if not isinstance(node, dict):
            return node
        if isinstance(node.get("$id"), str) and pointer:
            base, scope = urljoin(base or "", node["$id"]), pointer
        out: dict[str, Any] = {}
        for key, value in node.items():
            if key == "$id" and pointer:
                continue  # its scope is folded into the rewritten references
            if key in ("$ref", "$dynamicRef") and isinstance(value, str):
                out[key] = reference(value, base, scope)
            elif key in _DATA_KEYWORDS:
                out[key] = value  # values, not schemas: a "$ref" in them is data
            else:
                out[key] = walk(value, base, scope, f"{pointer}/{_escaped(key)}")
        return out

    def reference(value: str, base: str | None, scope: str) -> str:
        document_part, fragment = urldefrag(value)
        if not document_part:
            found: tuple[str, str] | None = (relative, scope)
        else:
            found = resolver.target(relative, base, value)
        if found is None:
            broken.append(value)
            return value
        reached.add(found[0])
        where = found[1] + fragment if not fragment or fragment.startswith("/") else fragment
        return f"{BASE}{found[0]}#{where}"

    root_base = document.get("$id") if isinstance(document, dict) and isinstance(document.get("$id"), str) else None
    rewritten = walk(document, root_base, "", "")
    if isinstance(rewritten, dict):
        rewritten["$id"] = BASE + relative
    return rewritten, reached, broken[0] if broken else None


def _scopes(node: Any, pointer: str, base: str | None) -> list[tuple[str, str | None]]:
    """``(JSON pointer, absolute $id)`` of every node declaring an ``$id`` (the root first)."""
    found: list[tuple[str, str | None]] = []
    if isinstance(node, dict):
        if isinstance(node.get("$id"), str):
            base = urldefrag(urljoin(base or "", node["$id"]))[0]
            found.append((pointer, base))
        for key, value in node.items():
            if key not in _DATA_KEYWORDS:
                found += _scopes(value, f"{pointer}/{_escaped(key)}", base)
    elif isinstance(node, list):
        for index, item in enumerate(node):
            found += _scopes(item, f"{pointer}/{index}", base)
    return found


_DATA_KEYWORDS = frozenset({"const", "enum", "examples", "default"})


def _escaped(key: str) -> str:
    return key.replace("~", "~0").replace("/", "~1")
