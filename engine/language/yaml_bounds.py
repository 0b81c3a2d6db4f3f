"""Bounds that keep one YAML file from exhausting the engine: size, nodes, alias copies, depth.

The engine reads route files at ``check``, at start and on every hot reload, so a file that
takes the process down takes every running route with it. Nine lines of anchors and aliases,
each list ten aliases of the one before (the "billion laughs"), expand to 10^9 nodes: the
loader grew to 5.3 GB and was still running after 60 s. Composing YAML into nodes costs too:
a 1 MB list of one-letter items is 500,000 nodes, 150 MB and several seconds to compose.

So before anything is composed, :func:`bound_problem` walks the parser's event stream (libyaml,
nothing kept but a stack and the expanded size of each anchor: a few kB whatever the file) and
refuses a file that

* holds more than :data:`MAX_NODES` nodes as written (1,000 routes in one file are ~28,000);
* copies more than :data:`MAX_ALIAS_NODES` nodes through its aliases (an alias copies the
  whole value of its anchor, aliases inside it included), counted as the alias is read, so the
  refusal comes at the alias that crosses the bound, with its line: ~10 events into the bomb;
* nests deeper than :data:`MAX_DEPTH` (route files nest ~8 levels; libyaml's own limit is
  1,000, past Python's recursion limit for the loader that turns nodes into values);
* uses an alias inside its own anchor (a recursive structure: no finite value).

:data:`MAX_FILE_BYTES` bounds what is read at all (:func:`read_bounded`). The walk costs one
extra parse, ~0.05 s for a 1,000-route file (280 kB) against ~0.4 s to compose it.
"""

from __future__ import annotations

from pathlib import Path

import yaml

MAX_FILE_BYTES = 4 * 1024 * 1024
"""Largest route, test or ``for_each`` file read (4 MiB: a 1,000-route file is ~280 kB)."""
MAX_NODES = 250_000
"""Most YAML nodes (mappings, lists, scalars, keys included) one file may hold as written."""
MAX_ALIAS_NODES = 100_000
"""Most nodes one file's aliases may copy in all (a route file sharing a sink through an
alias copies a handful per use)."""
MAX_DEPTH = 100
"""Deepest nesting of mappings and lists in one file."""

_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

_BOUND_HINT = "a bound that keeps one file from exhausting the engine"


class FileTooLarge(Exception):
    """A file over :data:`MAX_FILE_BYTES`; the message says so and states the bound."""


def read_bounded(path: Path) -> str:
    """The UTF-8 text of ``path``, read only up to :data:`MAX_FILE_BYTES` (a larger file is
    :class:`FileTooLarge` without being read whole)."""
    with path.open("rb") as handle:
        data = handle.read(MAX_FILE_BYTES + 1)
    if len(data) > MAX_FILE_BYTES:
        raise FileTooLarge(size_problem(path.stat().st_size))
    return data.decode("utf-8")


def size_problem(size: int) -> str:
    return (f"the file is {size:,} bytes, over the {MAX_FILE_BYTES:,} bytes ({MAX_FILE_BYTES // 1024 ** 2} MiB) "
            f"a route, test or for_each file may hold ({_BOUND_HINT}); split it into several files")


def bound_problem(text: str) -> tuple[int, str] | None:
    """``(line, message)`` of the first bound ``text`` passes, or None. A text that is not
    valid YAML is left to the loader, which says why where it stops."""
    if len(text.encode("utf-8")) > MAX_FILE_BYTES:
        return 1, size_problem(len(text.encode("utf-8")))
    loader = _Loader(text)
    stack: list[list] = []
    """Open collections: ``[anchor, expanded nodes so far]``."""
    sizes: dict[str, int] = {}
    """Expanded size of each anchor whose value is complete."""
    nodes = copied = 0
    try:
        while loader.check_event():
            event = loader.get_event()
            line = event.start_mark.line + 1 if event.start_mark else 1
            if isinstance(event, yaml.AliasEvent):
                if any(frame[0] == event.anchor for frame in stack):
                    return line, (f"invalid YAML: alias *{event.anchor} inside its own anchor &{event.anchor} "
                                  f"(a recursive structure has no end)")
                if event.anchor not in sizes:
                    continue  # undefined: the loader says so
                size = sizes[event.anchor]
                copied += size
                if copied > MAX_ALIAS_NODES:
                    return line, (f"alias *{event.anchor} copies {size:,} nodes, and the file's aliases more than "
                                  f"{MAX_ALIAS_NODES:,} in all ({_BOUND_HINT}: anchors of aliases of aliases grow "
                                  f"tenfold per line, the 'billion laughs'); write the values out, or use a route "
                                  f"template (for_each)")
                if stack:
                    stack[-1][1] += size
            elif isinstance(event, (yaml.ScalarEvent, yaml.CollectionStartEvent)):
                nodes += 1
                if nodes > MAX_NODES:
                    return line, (f"more than {MAX_NODES:,} YAML nodes in one file ({_BOUND_HINT}); "
                                  f"split it into several files")
                if isinstance(event, yaml.ScalarEvent):
                    if event.anchor is not None:
                        sizes[event.anchor] = 1
                    if stack:
                        stack[-1][1] += 1
                    continue
                stack.append([event.anchor, 1])
                if len(stack) > MAX_DEPTH:
                    return line, f"nested deeper than {MAX_DEPTH} levels ({_BOUND_HINT})"
            elif isinstance(event, yaml.CollectionEndEvent):
                anchor, size = stack.pop()
                if anchor is not None:
                    sizes[anchor] = size
                if stack:
                    stack[-1][1] += size
    except yaml.YAMLError:
        return None
    finally:
        loader.dispose()
    return None
