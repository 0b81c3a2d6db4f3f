"""memory: in the registry, but not a connector the suite can drive. It has no source (a route
cannot start from it), no library, no peer and no failure: its sink accepts every message at once
and sends it nowhere, so the route's ``remember`` keeps it (engine/endpoints/memory/__init__.py;
docs/route-language.md, Remembered values). Every case needs a source and a peer to inject into
and observe, so the harness takes part in none, each exclusion saying so; what memory does is
tested where it is used (tests/language/test_stores.py, tests/examples/test_vda5050.py)."""

from __future__ import annotations

from tests.endpoints.conformance.harness import CASES, Harness

WHY = ("memory has no source and no peer: its sink sends nothing anywhere (the route's remember keeps the "
       "message), so there is nothing to inject into or observe; tested by tests/language/test_stores.py")


class MemoryHarness(Harness):
    PROTOCOL = "memory"
    EXCLUDED = {case: WHY for case in CASES}


HARNESS = MemoryHarness
