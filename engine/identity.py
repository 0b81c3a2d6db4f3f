"""What identifies a connection for a reload: its settings, the contents of the files it
reads when it opens (signing keys), and the exclusive resource it holds (a listening port,
a serial device).

Computed once when the routes are loaded (off the event loop), so the reload plan
(:mod:`engine.plan`) compares plain values and never touches the disk.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Iterable, Mapping

from engine import endpoints
from engine.endpoints.base import Transport
from engine.redaction import json_default


def connection_fingerprint(protocol: str, settings: Mapping[str, Any]) -> str:
    """Hash of the protocol, the settings and the contents of the key files they name; a
    file that cannot be read hashes as missing (the endpoint's own check reports it)."""
    digest = hashlib.sha256(json.dumps([protocol, settings], sort_keys=True, default=json_default).encode())
    for name in sorted(connection_key_files(protocol, settings)):
        digest.update(b"\0" + name.encode() + b"\0")
        try:
            digest.update(hashlib.sha256(Path(name).expanduser().read_bytes()).digest())
        except OSError as exc:
            digest.update(f"unreadable: {exc.strerror}".encode())
    return digest.hexdigest()[:16]


def exclusive_resource(protocol: str, settings: Mapping[str, Any]) -> str | None:
    transport = _transport(protocol)
    return transport.exclusive_resource(settings) if transport is not None else None


def connection_key_files(protocol: str, settings: Mapping[str, Any]) -> Iterable[str]:
    """The files the connection reads when it opens (signing keys), as its transport names them."""
    transport = _transport(protocol)
    return list(transport.key_files(settings)) if transport is not None else ()


def _transport(protocol: str) -> Transport | None:
    try:
        return endpoints.transport(protocol)
    except Exception:  # not installed: the loader reports it
        return None
