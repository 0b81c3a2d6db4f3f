"""What identifies a connection for a reload: its settings, the contents of the files it
reads when it opens (signing keys), and the exclusive resource it holds (a listening port,
a serial device).

Computed once when the routes are loaded (off the event loop), so the reload plan
(:mod:`engine.running.plan`) compares plain values and never touches the disk.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Iterable, Mapping

from engine import endpoints
from engine.common.options import OptionError, parse
from engine.common.redaction import json_default
from engine.endpoints.base import Transport


def connection_fingerprint(protocol: str, settings: Mapping[str, Any], options: Any = None) -> str:
    """Hash of the protocol, the settings as written and the contents of the key files they
    name (read from the typed ``options`` when given); a file that cannot be read hashes as
    missing (the endpoint's own check reports it)."""
    digest = hashlib.sha256(json.dumps([protocol, settings], sort_keys=True, default=json_default).encode())
    for name in sorted(connection_key_files(protocol, settings if options is None else options)):
        digest.update(b"\0" + name.encode() + b"\0")
        try:
            digest.update(hashlib.sha256(Path(name).expanduser().read_bytes()).digest())
        except OSError as exc:
            digest.update(f"unreadable: {exc.strerror}".encode())
    return digest.hexdigest()[:16]


def exclusive_resource(protocol: str, options: Any) -> str | None:
    """The resource the connection with these options (typed, or a mapping) holds; None
    when there is none or they are invalid (``check`` reports those)."""
    transport = _transport(protocol)
    options = _typed(transport, options)
    return transport.exclusive_resource(options) if transport is not None and options is not None else None


def connection_key_files(protocol: str, options: Any) -> Iterable[str]:
    """The files the connection with these options (typed, or a mapping) reads when it opens
    (signing keys), as its transport names them."""
    transport = _transport(protocol)
    options = _typed(transport, options)
    return list(transport.key_files(options)) if transport is not None and options is not None else ()


def _typed(transport: Transport | None, options: Any) -> Any:
    if transport is None or not isinstance(options, Mapping):
        return options
    try:
        return parse(transport.connection_options, options)
    except OptionError:
        return None


def _transport(protocol: str) -> Transport | None:
    try:
        return endpoints.transport(protocol)
    except Exception:  # not installed: the loader reports it
        return None
