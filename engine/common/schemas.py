"""Canonical JSON Schemas: the vocabulary every route maps into.

Schemas are files ``schemas/<name>.v<N>.json``. A route names ``weed_detection`` (the
newest version) or ``weed_detection.v1`` (pinned). A standard's own schemas keep their family
in one subdirectory level: ``schemas/vda5050/order.v2.json`` is ``vda5050/order`` (its licence
and provenance beside it, apart from the project's vocabulary); deeper levels are not read.
Several directories may be given, a later one over the earlier, and ``$ref`` names a schema
file whatever the ``$id`` (engine/common/schema_files.py). Validators are built once per schema
and shared by every route that uses it; ``$ref`` between schema files resolves through a
registry of the directories, offline, so the envelope is written once.

Messages are validated with jsonschema-rs (a compiled, complete Draft 2020-12
implementation: about 1 us per message here against 200 us for the pure-Python
``jsonschema``, which stays in use for checking the schema files themselves).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence
from urllib.parse import urldefrag, urljoin

import jsonschema
import jsonschema_rs
import orjson

from engine.common.schema_files import FILE_NAME, Resolver, SchemaFile, layered, rewrite


class SchemaError(ValueError):
    """A message does not satisfy its canonical schema; the text names the field."""


_ORJSON_OPTIONS = (
    orjson.OPT_SORT_KEYS
    | orjson.OPT_PASSTHROUGH_SUBCLASS
    | orjson.OPT_PASSTHROUGH_DATETIME
    | orjson.OPT_PASSTHROUGH_DATACLASS
)
_FLOAT_FORMS_THAT_DIFFER = re.compile(rb"[0-9]e[-+]|0\.0000")
"""orjson writes ``1e-7`` and ``0.000015`` where Python writes ``1e-07`` and ``1.5e-05``;
output with an exponent or a number below 1e-4 anywhere (rare in field data, and a match
inside a string only costs time) takes the standard library's path."""
_LONG_NUMBER = re.compile(rb"[0-9]{20}|-[0-9]{19}")
"""Integers orjson may read as a float instead (beyond -2^63 .. 2^64-1): 20 digits or more,
or negative with 19. A 19-digit positive integer is exact in orjson, and a nanosecond
timestamp has 19 digits: the fleet benchmark's robots (bench/fleet.py) send one in every
message, and matching those sent every message through the standard library's parser."""
"""orjson parses integers beyond 64 bits as floats; the standard library keeps them exact."""
_DIGITS_AS_ZERO = bytes.maketrans(b"123456789", b"000000000")
_NINETEEN_DIGITS = b"0" * 19
_TWENTY_DIGITS = b"0" * 20
_MINUS_NINETEEN_DIGITS = b"-" + _NINETEEN_DIGITS
"""Both forms of :data:`_LONG_NUMBER` hold 19 digits in a row: with every digit turned into a
zero (``bytes.translate``) that is one substring search, 0.4 us for a 100-byte GNSS fix where
the regular expression takes 2.1 us, a sixth of the ROS 2 -> AMQP route's conversion
(bench/results/2026-11-23/ratios-v2). The expression decides only when such a run is there."""


def canonical_bytes(data: Any) -> bytes:
    """Deterministic canonical JSON: sorted keys, compact, UTF-8, no NaN/Infinity.

    The bytes are exactly ``json.dumps(data, sort_keys=True, separators=(",", ":"),
    ensure_ascii=False, allow_nan=False)`` encoded as UTF-8 (the format every stored and
    published canonical message has had); orjson produces them about ten times faster and
    the standard library is used for the few inputs where the two could differ: types
    orjson does not take as plain JSON (subclasses, non-string keys, integers beyond
    64 bits), exponents and numbers below 1e-4, and ``null`` that may stand for
    NaN/Infinity (orjson writes those as null, the canonical form rejects them).
    """
    try:
        out = orjson.dumps(data, option=_ORJSON_OPTIONS)
    except TypeError:
        return _stdlib_canonical_bytes(data)
    # The screens run on the text: ``bytes in bytes`` first tries the needle as an integer and
    # raises and clears a TypeError each time, so the four took 0.85-1.5 us for a GNSS fix's
    # 137 bytes, four times orjson's own work, where decoding once and searching the str takes
    # 0.56 (UTF-8 never encodes a non-ASCII character with ASCII bytes: the same matches).
    text = out.decode("utf-8")
    if ("e-" in text or "e+" in text or "0.0000" in text) and _FLOAT_FORMS_THAT_DIFFER.search(out) is not None:
        return _stdlib_canonical_bytes(data)
    if "null" in text and _has_non_finite(data):
        return _stdlib_canonical_bytes(data)
    return out


def _stdlib_canonical_bytes(data: Any) -> bytes:
    try:
        return json.dumps(
            data, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
        ).encode("utf-8")
    except ValueError as exc:
        raise SchemaError(f"not representable as canonical JSON: {exc}") from None


def _has_non_finite(value: Any) -> bool:
    if type(value) is float:
        return not math.isfinite(value)
    if type(value) is dict:
        return any(_has_non_finite(v) for v in value.values())
    if type(value) is list or type(value) is tuple:
        return any(_has_non_finite(v) for v in value)
    return False


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


MAX_DEPTH = 1024
"""orjson's nesting limit, and so the engine's: deeper JSON is a decode failure."""


def parse_json(body: bytes) -> Any:
    """Strict JSON: NaN/Infinity are rejected, errors say where.

    orjson parses; whatever it refuses (invalid JSON, a BOM, numbers out of its range) or
    might read differently (integers beyond 64 bits) goes through the standard library, so
    results and error messages are exactly the standard library's.
    """
    if not _may_hold_long_number(body):
        try:
            return orjson.loads(body)
        except orjson.JSONDecodeError as exc:
            if str(exc).startswith("depth limit exceeded"):
                # one limit, whoever parses: the standard library's depends on the caller's stack
                raise SchemaError(f"invalid JSON: nested deeper than {MAX_DEPTH} levels") from None
    return _stdlib_parse_json(body)


def _may_hold_long_number(body: bytes | bytearray) -> bool:
    """Whether :data:`_LONG_NUMBER` matches ``body``. With every digit turned into a zero, a
    run of digits is a run of zeros (only digits become zeros), so the expression's two forms
    are two substring searches in the translated body: the expression itself cost 2.1-2.9 us a
    message where a 19-digit run is common (a nanosecond timestamp in every message of
    bench/fleet.py's robots: 1.9 % of the engine's GIL samples), the searches 0.6 us in all."""
    try:
        digits = body.translate(_DIGITS_AS_ZERO)
    except (AttributeError, TypeError):  # not bytes or bytearray: the expression alone decides
        return _LONG_NUMBER.search(body) is not None
    if digits.find(_NINETEEN_DIGITS) < 0:  # find: no int attempt, as ``in`` makes
        return False
    return digits.find(_TWENTY_DIGITS) >= 0 or digits.find(_MINUS_NINETEEN_DIGITS) >= 0


def _stdlib_parse_json(body: bytes) -> Any:
    try:
        # decoded strictly first: json.loads(bytes) lets UTF-8-encoded surrogates through
        return json.loads(body.decode("utf-8"), parse_constant=_reject_constant)
    except UnicodeDecodeError as exc:
        raise SchemaError(f"invalid JSON: not UTF-8 at byte {exc.start}") from None
    except json.JSONDecodeError as exc:
        raise SchemaError(f"invalid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except ValueError as exc:
        raise SchemaError(f"invalid JSON: {exc}") from None


def error_path(path: Any) -> str:
    out = "$"
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else f".{part}"
    return out


@dataclass(frozen=True)
class CanonicalSchema:
    name: str
    version: int
    path: Path
    validate: Callable[[Any], None]
    digest: str = ""
    """Hash of this schema's content and of every schema it reaches through ``$ref``, so a
    reload sees an edit of the envelope in every route whose schema refers to it."""


class SchemaRegistry:
    """All schemas of one or more directories (a later one over the earlier: see
    engine/common/schema_files.py), loaded and compiled together."""

    def __init__(self, directories: Path | Sequence[Path]) -> None:
        self.directories: tuple[Path, ...] = (directories,) if isinstance(directories, Path) else tuple(directories)
        self._schemas: dict[str, CanonicalSchema] = {}
        self.problems: list[tuple[Path, str]] = []
        self.files: dict[str, SchemaFile] = {}
        """Every schema file by its name in the layered tree, with the files it replaces."""
        self._documents: dict[Path, dict[str, Any]] = {}
        self._by_id: dict[str, Any] = {}
        self._declared: dict[Path, Declared] = {}
        self._reached: dict[str, set[str]] = {}
        """``name.vN`` -> the files (relative names) it reaches through ``$ref``, its own included."""
        self._load()
        self._by_id.update((doc["$id"], doc) for doc in self._documents.values())

    def _load(self) -> None:
        self.files, problems = layered(self.directories)
        self.problems += problems
        read: dict[str, Any] = {}
        for relative, schema_file in self.files.items():
            try:
                text = schema_file.path.read_text(encoding="utf-8")
                document = json.loads(text)
                _check_schema(text)
            except (OSError, ValueError) as exc:
                self.problems.append((schema_file.path, f"invalid JSON: {exc}"))
                continue
            except jsonschema.SchemaError as exc:
                self.problems.append((schema_file.path, f"invalid JSON Schema: {exc.message}"))
                continue
            read[relative] = document
        closures = self._closures(read)
        documents = {self.files[relative].path: doc for relative, doc in closures.items()}
        self._documents = {path: doc for path, (doc, _) in documents.items()}
        try:
            registry = jsonschema_rs.Registry([(doc["$id"], doc) for doc, _ in documents.values()])
        except (jsonschema_rs.ReferencingError, ValueError) as exc:  # a reference form we do not follow
            self.problems.append((self.directories[-1], f"cannot resolve the schemas' $refs: {exc}"))
            return
        for relative, (document, reached) in closures.items():
            path = self.files[relative].path
            match = FILE_NAME.match(path.name)
            assert match
            name, version = match["name"], int(match["version"])
            if "/" in relative:
                name = f"{relative.split('/')[0]}/{name}"
            try:
                validator = jsonschema_rs.validator_for(document, registry=registry, offline=True)
            except (jsonschema_rs.ReferencingError, ValueError) as exc:
                self.problems.append((path, f"cannot compile: {exc}"))
                continue
            digest = hashlib.sha256(
                json.dumps([closures[r][0] for r in sorted(reached)], sort_keys=True).encode()
            ).hexdigest()[:16]
            entry = CanonicalSchema(name, version, path, _validating(f"{name}.v{version}", validator), digest)
            self._reached[f"{name}.v{version}"] = reached
            self._schemas[f"{name}.v{version}"] = entry
            newest = self._schemas.get(name)
            if newest is None or newest.version < version:
                self._schemas[name] = entry

    def _closures(self, read: dict[str, Any]) -> dict[str, tuple[dict[str, Any], set[str]]]:
        """Each schema file rewritten (engine/common/schema_files.py: its ``$ref``s absolute,
        by file name), with the files its ``$ref``s reach, transitively. A ``$ref`` to no file
        of the directories (or to one not valid) is a problem of the referring file and of
        every file that refers to it, so none of them is half-loaded."""
        resolver = Resolver(read)
        direct: dict[str, set[str]] = {}
        rewritten: dict[str, dict[str, Any]] = {}
        broken: dict[str, str] = {}
        where = ", ".join(map(str, self.directories))
        for relative, document in read.items():
            rewritten[relative], reached, unresolved = rewrite(relative, document, resolver)
            direct[relative] = {relative} | reached
            if unresolved is not None:
                broken[relative] = f"$ref {unresolved!r} does not resolve to a schema file of {where}"
        closures: dict[str, tuple[dict[str, Any], set[str]]] = {}
        for relative in read:
            reached_all: set[str] = set()
            frontier = [relative]
            while frontier:
                current = frontier.pop()
                if current not in reached_all:
                    reached_all.add(current)
                    frontier.extend(direct.get(current, ()))
            bad = sorted(r for r in reached_all if r in broken or r not in read)
            path = self.files[relative].path
            if relative in broken:
                self.problems.append((path, broken[relative]))
            elif bad:
                self.problems.append((path, f"refers to {bad[0]}, which does not load"))
            else:
                closures[relative] = (rewritten[relative], reached_all)
        return closures

    def files_used(self, names: Sequence[str]) -> list[SchemaFile]:
        """The files schemas ``names`` (``position``, ``position.v1``) were read from, with
        every file they reach through ``$ref``, by name in the layered tree."""
        used: set[str] = set()
        for name in names:
            entry = self._schemas.get(name)
            if entry is not None:
                used |= self._reached[f"{entry.name}.v{entry.version}"]
        return [self.files[relative] for relative in sorted(used)]

    def names(self) -> list[str]:
        return sorted(self._schemas)

    def declared(self, name: str) -> Declared | None:
        """The keys schema ``name`` declares (for ``check``'s warnings); None if it is unknown."""
        entry = self._schemas.get(name)
        if entry is None or entry.path not in self._documents:
            return None
        if entry.path not in self._declared:  # one per schema file: every route using it shares it
            document = self._documents[entry.path]
            self._declared[entry.path] = Declared([(document, document["$id"])], self._by_id)
        return self._declared[entry.path]

    def get(self, name: str) -> CanonicalSchema | None:
        return self._schemas.get(name)

    def bundled(self, name: str) -> dict[str, Any] | None:
        """Schema ``name`` as one self-contained document: every schema file its ``$ref``s reach
        is embedded under ``$defs`` with its own ``$id`` (JSON Schema 2020-12 bundling), so the
        references resolve without the directory (a recording's or a Foxglove channel's schema)."""
        entry = self._schemas.get(name)
        if entry is None or entry.path not in self._documents:
            return None
        root = self._documents[entry.path]
        reached = [self._documents[self.files[relative].path] for relative in sorted(self._reached[f"{entry.name}.v{entry.version}"])
                   if self.files[relative].path != entry.path and self.files[relative].path in self._documents]
        if not reached:
            return root
        embedded = {f"bundled_{index}": document for index, document in enumerate(reached)}
        return {**root, "$defs": {**root.get("$defs", {}), **embedded}}


class Declared:
    """The object keys a schema declares, for ``check`` to warn about a key a mapping sets
    that the schema never names (a misspelt optional field passes validation unnoticed).

    Read from the schema's JSON: ``properties`` wherever they are (through ``$ref``,
    ``allOf``/``anyOf``/``oneOf``, ``then``/``else``, ``dependentSchemas``), a key declared
    in any branch counting as declared; ``items`` for the elements of arrays. A schema is
    *open* (any key goes, nothing to warn about) when it declares no property at all, or
    allows more on purpose (``additionalProperties`` other than false, ``patternProperties``).
    It is *closed* when it allows no key but those it declares: ``additionalProperties: false``
    (or ``unevaluatedProperties: false``) at the node, through ``$ref``, in an ``allOf`` branch,
    or in every branch of an ``anyOf``/``oneOf`` (a field read there that it does not declare
    is always null: an error for ``check``, where elsewhere it is a warning).
    """

    def __init__(self, nodes: list[tuple[Any, str]], by_id: dict[str, Any]) -> None:
        self._by_id = by_id
        self._properties: dict[str, list[tuple[Any, str]]] = {}
        self._items: list[tuple[Any, str]] = []
        self._open = False
        self._children: dict[str, Declared] = {}
        self._elements: Declared | None = None
        seen: set[int] = set()
        for node, base in nodes:
            self._collect(node, base, seen)
        self.open = self._open or not self._properties
        self.keys = sorted(self._properties)
        self.closed = not self.open and all(self._closed(node, base, 0) for node, base in nodes)

    def child(self, key: str) -> Declared:
        """What the schema declares inside ``key``'s value (built once, then kept)."""
        if key not in self._children:
            self._children[key] = Declared(self._properties.get(key, []), self._by_id)
        return self._children[key]

    def items(self) -> Declared:
        """What the schema declares for the elements of a list value."""
        if self._elements is None:
            self._elements = Declared(self._items, self._by_id)
        return self._elements

    def _collect(self, node: Any, base: str, seen: set[int]) -> None:
        if not isinstance(node, dict) or id(node) in seen:
            self._open = self._open or node is True
            return
        seen.add(id(node))
        base = urljoin(base, node["$id"]) if isinstance(node.get("$id"), str) else base
        if isinstance(node.get("$ref"), str):
            target, target_base = self._resolve(urljoin(base, node["$ref"]))
            if target is None:
                self._open = True  # a reference not followed here: assume it allows anything
            else:
                self._collect(target, target_base, seen)
        for key, subschema in (node.get("properties") or {}).items():
            self._properties.setdefault(key, []).append((subschema, base))
        more = node.get("additionalProperties", False)
        if more is not False and more != {"not": {}} or node.get("patternProperties"):
            self._open = True
        for keyword in ("allOf", "anyOf", "oneOf"):
            for branch in node.get(keyword) or ():
                self._collect(branch, base, seen)
        for keyword in ("then", "else"):
            if keyword in node:
                self._collect(node[keyword], base, seen)
        for branch in (node.get("dependentSchemas") or {}).values():
            self._collect(branch, base, seen)
        items = node.get("items")
        if isinstance(items, (dict, bool)):
            self._items.append((items, base))
        self._items.extend((item, base) for item in node.get("prefixItems") or ())

    def _closed(self, node: Any, base: str, depth: int) -> bool:
        """Whether ``node`` allows no object key but those declared (see the class docstring)."""
        if not isinstance(node, dict) or depth > 32:
            return node is False
        if node.get("additionalProperties") is False or node.get("unevaluatedProperties") is False:
            return True
        base = urljoin(base, node["$id"]) if isinstance(node.get("$id"), str) else base
        if isinstance(node.get("$ref"), str):
            target, target_base = self._resolve(urljoin(base, node["$ref"]))
            if target is not None and self._closed(target, target_base, depth + 1):
                return True
        if any(self._closed(branch, base, depth + 1) for branch in node.get("allOf") or ()):
            return True
        return any(node.get(keyword) and all(self._closed(branch, base, depth + 1) for branch in node[keyword])
                   for keyword in ("anyOf", "oneOf"))

    def _resolve(self, uri: str) -> tuple[Any, str]:
        document_uri, fragment = urldefrag(uri)
        node = self._by_id.get(document_uri)
        for token in (fragment.split("/")[1:] if fragment.startswith("/") else []):
            token = token.replace("~1", "/").replace("~0", "~")
            node = node.get(token) if isinstance(node, dict) else None
        return node, document_uri


@functools.lru_cache(maxsize=512)
def _check_schema(text: str) -> None:
    """Check a schema against its meta-schema, once per content: the pure-Python check is
    most of a reload's compile time, and a reload usually leaves every schema as it was."""
    document = json.loads(text)
    jsonschema.validators.validator_for(document).check_schema(document)


def _validating(label: str, validator: Any) -> Callable[[Any], None]:
    is_valid = validator.is_valid

    def validate(data: Any) -> None:
        if not is_valid(data):
            error = next(iter(validator.iter_errors(data)))
            raise SchemaError(f"schema {label}: {error_path(error.instance_path)}: {error.message}")

    return validate


__all__ = [
    "CanonicalSchema",
    "Declared",
    "SchemaError",
    "SchemaRegistry",
    "canonical_bytes",
    "parse_json",
]
