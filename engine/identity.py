"""What identifies a connection for a reload: its settings, the contents of the files it
reads when it opens (signing keys), and the exclusive resource it holds (a listening port,
a serial device).

Computed once when the routes are loaded (off the event loop), so the reload plan
(:mod:`engine.plan`) compares plain values and never touches the disk.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

from engine import endpoints
from engine.endpoints.base import Transport
from engine.redaction import json_default


def connection_fingerprint(protocol: str, settings: Mapping[str, Any]) -> str:
    """Hash of the protocol, the settings and the contents of the key files they name; a
    file that cannot be read hashes as missing (the endpoint's own check reports it)."""
    digest = hashlib.sha256(json.dumps([protocol, settings], sort_keys=True, default=json_default).encode())
    for name in sorted(_key_files(protocol, settings)):
        digest.update(b"\0" + name.encode() + b"\0")
        try:
            digest.update(hashlib.sha256(Path(name).expanduser().read_bytes()).digest())
        except OSError as exc:
            digest.update(f"unreadable: {exc.strerror}".encode())
    return digest.hexdigest()[:16]


def exclusive_resource(protocol: str, settings: Mapping[str, Any]) -> str | None:
    transport = _transport(protocol)
    if transport is not None and _overrides(transport, "exclusive_resource"):
        return transport.exclusive_resource(settings)
    if protocol == "mavlink":
        return mavlink_exclusive_resource(settings)
    return None


def _key_files(protocol: str, settings: Mapping[str, Any]) -> Iterable[str]:
    transport = _transport(protocol)
    if transport is not None and _overrides(transport, "key_files"):
        return list(transport.key_files(settings))
    if protocol == "mavlink":
        return mavlink_key_files(settings)
    return ()


def _transport(protocol: str) -> Transport | None:
    try:
        return endpoints.transport(protocol)
    except Exception:  # not installed: the loader reports it
        return None


def _overrides(transport: Transport, method: str) -> bool:
    return getattr(type(transport), method) is not getattr(Transport, method)


# Interim readings of MAVLink connection settings, until the MAVLink package overrides
# ``MavlinkTransport.exclusive_resource`` and ``key_files`` (engine/endpoints/mavlink.py);
# once it does, these are no longer called and can go.


def mavlink_exclusive_resource(settings: Mapping[str, Any]) -> str | None:
    """``udpin:HOST:PORT`` -> ``udp:PORT`` (one socket per port, whatever the host),
    ``tcpin:`` -> ``tcp:PORT``, a device path -> ``serial:<real path>``; port 0, ``udpout:``
    and ``tcp:`` hold nothing exclusively."""
    url = settings.get("url")
    if not isinstance(url, str):
        return None
    scheme, sep, rest = url.partition(":")
    if sep and scheme in ("udpin", "udp", "tcpin"):
        port = rest.rpartition(":")[2]
        if not port.isdigit() or int(port) == 0:
            return None
        return f"{'tcp' if scheme == 'tcpin' else 'udp'}:{int(port)}"
    if url.startswith("/"):
        return "serial:" + os.path.realpath(url.partition(",")[0])
    return None


def mavlink_key_files(settings: Mapping[str, Any]) -> list[str]:
    signing = settings.get("signing")
    if isinstance(signing, Mapping) and isinstance(signing.get("key_file"), str):
        return [signing["key_file"]]
    return []
