"""Did-you-mean suggestions for misspelt names (types, messages, fields, functions, schemas).

One place so every error message suggests the same way: difflib's ratio, which catches a
dropped, doubled or swapped letter (``longitud``, ``GLOBAL_POSITON_INT``) without suggesting
something unrelated.
"""

from __future__ import annotations

import difflib
from typing import Iterable


def closest(word: str, choices: Iterable[str]) -> str | None:
    """The choice most like ``word``, if any is close enough (case-insensitive)."""
    options = {str(choice).lower(): str(choice) for choice in choices}
    matches = difflib.get_close_matches(str(word).lower(), list(options), n=1, cutoff=0.6)
    return options[matches[0]] if matches else None


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` to append to an error message, or ``""``."""
    match = closest(word, choices)
    return f"; did you mean {match!r}?" if match is not None and match != word else ""
