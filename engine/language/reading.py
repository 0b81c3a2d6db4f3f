"""Reading a routes directory: which files are route files, the ``for_each`` item files they
name, and the agents table every file may add to; problems are collected, never raised."""

from __future__ import annotations

import json
import re
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import jsonschema

from engine.common.redaction import revealed
from engine.language import agents as agents_table
from engine.language.route_yaml import Document, Path_, Problem, parse_document
from engine.language.templates import is_items_text
from engine.language.yaml_bounds import FileTooLarge, read_bounded

ROUTE_FILE_SCHEMA: dict[str, Any] = json.loads(
    resources.files("engine.language").joinpath("route_file.schema.json").read_text(encoding="utf-8")
)


ROUTE_FILE_VALIDATOR = jsonschema.Draft202012Validator(ROUTE_FILE_SCHEMA)


def route_files(directory: Path) -> list[Path]:
    """``*.yaml``/``*.yml`` files, skipping editors' hidden and backup files; a single file
    given instead of a directory is a directory of one file."""
    if directory.is_file():
        return [directory]
    return sorted(
        path
        for pattern in ("*.yaml", "*.yml")
        for path in directory.glob(pattern)
        if path.is_file() and not path.name.startswith(".") and not path.name.endswith("~")
        and not is_test_file(path)
    )


def is_test_file(path: Path) -> bool:
    """``*.test.yaml`` files hold route tests (``rabbitros-engine test``), never routes."""
    return path.name.endswith((".test.yaml", ".test.yml"))


_ITEMS_VALIDATOR = jsonschema.Draft202012Validator({"type": "array", "items": {"type": "object"}})


class ItemFiles:
    """``for_each`` files as the loader reads them: each once per load, with ``${VAR}`` and
    line numbers, relative to the route file naming it; those in the routes directory come
    from the texts already read (they are not route files)."""

    def __init__(self, env: Mapping[str, str], problems: list[Problem]) -> None:
        self.env = env
        self.problems = problems
        self.texts: dict[Path, str] = {}
        """List-topped files of the routes directory, by absolute path."""
        self.read: dict[Path, list[Any] | None] = {}
        self.agents: agents_table.Table = {}
        """The directory's agents table: ``for_each: agents`` expands over it."""

    def reader(self, route_file: Path) -> Callable[[str, Path_], tuple[list[Any] | None, str | None]]:
        def read(name: str, where: Path_) -> tuple[list[Any] | None, str | None]:
            if name == agents_table.AGENTS:
                if not self.agents:
                    return None, "for_each: agents expands over the agents table, and no file has a top-level agents: mapping"
                return agents_table.items(self.agents), None
            path = (route_file.parent / name).resolve()
            if path not in self.read:
                self.read[path] = self._load(path)
            items = self.read[path]
            if items is None:
                return None, f"route template: for_each file {name!r} ({path}) is not a readable YAML list of objects (see its own problems)"
            return items, None

        return read

    def _load(self, path: Path) -> list[Any] | None:
        text = self.texts.get(path)
        if text is None:
            try:
                text = read_bounded(path)
            except FileTooLarge as exc:
                self.problems.append(Problem(str(path), 1, str(exc)))
                return None
            except (OSError, UnicodeDecodeError) as exc:
                self.problems.append(Problem(str(path), 0, f"cannot read for_each file: {exc}"))
                return None
        if not is_items_text(text) and not any(line.strip() and not line.lstrip().startswith("#") for line in text.splitlines()):
            return []  # every item deleted (comments may stay): no routes from the template
        before = len(self.problems)
        document = parse_document(str(path), text, self.env, self.problems, _ITEMS_VALIDATOR)
        if document is None or len(self.problems) > before:
            return None
        return document.data if isinstance(document.data, list) else None

    def unused(self) -> list[Problem]:
        return [Problem(str(path), 1, "a YAML list, so not a route file; no route names it in for_each (left out)")
                for path in sorted(self.texts) if path not in self.read]


_AGENTS_KEY = re.compile(r"^agents\s*:", re.MULTILINE)


_VARIABLE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def read_agents_table(texts: list[tuple[Path, str]], env: Mapping[str, str], problems: list[Problem]) -> dict[str, dict[str, Any]]:
    """The directory's agents table (engine/language/agents.py): every file's top-level ``agents:``,
    read before the routes are expanded (``for_each: agents`` needs it); names unique across
    the directory. The schema's problems are reported where the file itself is read."""
    table: dict[str, dict[str, Any]] = {}
    where_defined: dict[str, tuple[str, int]] = {}
    for path, text in texts:
        if not _AGENTS_KEY.search(text):
            continue
        document = parse_document(str(path), text, env, [], ROUTE_FILE_VALIDATOR, keep_invalid=True)
        if document is None:
            continue
        body = document.data.get(agents_table.AGENTS)
        if not isinstance(body, dict):
            continue
        for name, entry in body.items():
            line = document.line((agents_table.AGENTS, name))
            if name in where_defined:
                first_file, first_line = where_defined[name]
                problems.append(Problem(str(path), line, f"agent {name!r} is already defined at {first_file}:{first_line}"
                                                         f"{together_hint(document, first_file)}"))
                continue
            where_defined[name] = (str(path), line)
            if not isinstance(entry, dict) or any(not isinstance(key, str) or not _VARIABLE.match(key) for key in entry):
                continue  # the schema says what it should be
            if agents_table.AGENT in entry:
                problems.append(Problem(str(path), line, f"agent {name!r}: {agents_table.AGENT!r} is the agent's name "
                                                         f"(for_each: agents gives it as {{agent}}); use another key"))
                continue
            table[name] = revealed(entry)
    return table


def together_hint(document: Document, other_file: str) -> str:
    """For a name defined in two files: why both count (alternatives side by side, as two
    versions of one example, collide)."""
    if other_file == document.file:
        return ""
    return " (every file of a routes directory is loaded together: keep alternative files in separate directories)"


def document_items(document: Document, key: str, kind: type[Any]) -> Iterator[Any]:
    """``connections`` (a mapping's items) or ``routes`` (a list's items, numbered) of a
    document; nothing when the value is of another shape (the schema reported it)."""
    value = document.data.get(key)
    if not isinstance(value, kind):
        return iter(())
    return iter(value.items()) if kind is dict else enumerate(value)
