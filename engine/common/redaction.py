"""Secrets from route files, wrapped so that no later message can carry them.

A value is a secret when it holds an AMQP-style URL password (``scheme://user:pass@host``)
or comes from a ``${VAR}`` whose name says it is one (``*PASSWORD*``, ``*PASSWD*``,
``*SECRET*``, ``*TOKEN*``, ``*CREDENTIAL*``, ``*KEY*``). The route loader wraps such values
in :class:`Secret` as it parses the files: ``str``, ``repr``, ``format`` and ``json.dumps(...,
default=str)`` all give the redacted text, so ``check`` output, JSON-schema errors, logs,
the status file and dead-letter headers cannot show the value. Only an endpoint, at the
moment it connects, calls :func:`reveal`.

Equality and hashing use the real value, so changing a password is a configuration change
(a reload reconnects); :attr:`Secret.digest` stands for it wherever a fingerprint is made.
"""

from __future__ import annotations

import hashlib
import re
from typing import Any
from urllib.parse import urlsplit

SECRET_NAME = re.compile(r"PASSWORD|PASSWD|SECRET|TOKEN|CREDENTIAL|KEY", re.IGNORECASE)
"""Environment variable names whose values are secrets."""
MASK = "***"
_URL_PASSWORD = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://[^:/?#@\s]*:)(?P<password>[^@/?#\s]*)(?P<tail>@)")


class Secret:
    """A configuration value that must never be shown; ``reveal()`` gives it back."""

    __slots__ = ("_value", "_shown")

    def __init__(self, value: str, shown: str | None = None) -> None:
        self._value = value
        self._shown = redact_text(value) if shown is None else shown

    def reveal(self) -> str:
        return self._value

    @property
    def digest(self) -> str:
        """A stand-in for the value in fingerprints and connection keys."""
        return "secret:" + hashlib.sha256(self._value.encode()).hexdigest()[:16]

    def __str__(self) -> str:
        return self._shown

    def __repr__(self) -> str:
        return repr(self._shown)

    def __format__(self, spec: str) -> str:
        return format(self._shown, spec)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Secret) and other._value == self._value

    def __hash__(self) -> int:
        return hash(("Secret", self._value))

    def __reduce__(self) -> Any:  # a pickled or copied Secret stays wrapped
        return (Secret, (self._value, self._shown))


def reveal(value: Any) -> Any:
    """The real value of a :class:`Secret`; anything else unchanged."""
    return value.reveal() if isinstance(value, Secret) else value


def redact_urls(text: str) -> str:
    """``text`` with every URL password replaced by ``***`` (for any text: log lines, errors)."""
    return _URL_PASSWORD.sub(lambda m: m["head"] + MASK + m["tail"], text) if "://" in text else text


def redact_text(text: str) -> str:
    """How a secret value is shown: a URL with its password as ``***``; anything else that is
    not a URL (a token, a key) as ``***`` alone."""
    if not text:
        return text
    return redact_urls(text) if "://" in text else MASK


def has_url_password(text: str) -> bool:
    try:
        return bool(urlsplit(text).password)
    except ValueError:
        return bool(_URL_PASSWORD.search(text))


def is_secret_name(name: str) -> bool:
    return bool(SECRET_NAME.search(name))


def _map_secrets(value: Any, replace: Any) -> Any:
    if isinstance(value, Secret):
        return replace(value)
    if isinstance(value, dict):
        return {key: _map_secrets(item, replace) for key, item in value.items()}
    if isinstance(value, list):
        return [_map_secrets(item, replace) for item in value]
    return value


def shown(value: Any) -> Any:
    """A copy of a parsed document in which every Secret is its redacted text: what schema
    validation and error messages see."""
    return _map_secrets(value, str)


def revealed(value: Any) -> Any:
    """A copy with every Secret unwrapped (for places that are not credentials)."""
    return _map_secrets(value, Secret.reveal)


def json_default(value: Any) -> Any:
    """``json.dumps(default=...)`` for fingerprints: a Secret counts by its digest."""
    if isinstance(value, Secret):
        return value.digest
    return str(value)
