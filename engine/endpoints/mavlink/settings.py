"""Connection settings (YAML ``connections.<name>.mavlink``), parsed once into a typed value.

Every problem is collected with the key it belongs to, so ``check`` names the file, route and
field; the connection itself is built from the resulting :class:`LinkConfig`.
"""

from __future__ import annotations

import contextlib
import math
import os
import termios
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from engine.endpoints.mavlink.codec import MESSAGES, RADIO_STATUS, mavlink2
from engine.endpoints.mavlink.tunnel import TunnelSettings

_SETTINGS = {"url", "baud", "source_system", "source_component", "signing", "rate", "heartbeat", "mav_type", "tunnel"}
_SIGNING = {"key_file", "key_env", "link_id", "timestamp_file", "allow_unsigned"}



@dataclass(frozen=True, slots=True)
class Address:
    kind: str
    """serial | udpin | udpout | tcp | tcpin"""
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600


def parse_address(url: Any, baud: Any = None) -> Address:
    """pymavlink-style connection string -> :class:`Address`; ValueError names the problem."""
    if not isinstance(url, str) or not url.strip():
        raise ValueError("url must be a non-empty string")
    scheme, sep, rest = url.partition(":")
    if sep and scheme in ("udpin", "udpout", "udp", "tcp", "tcpin"):
        host, colon, port = rest.rpartition(":")
        if not colon or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ValueError(f"bad url {url!r}: expected {scheme}:HOST:PORT")
        kind = "udpin" if scheme == "udp" else scheme
        if not host:
            if kind in ("udpout", "tcp"):
                raise ValueError(f"bad url {url!r}: {kind} needs a host")
            host = "0.0.0.0"
        if kind in ("udpout", "tcp") and int(port) == 0:
            raise ValueError(f"bad url {url!r}: port 0")
        if baud is not None:
            raise ValueError("baud applies to serial links only")
        return Address(kind, host.strip("[]"), int(port))
    device, comma, inline_baud = url.partition(",")
    if not device.startswith("/"):
        raise ValueError(f"bad url {url!r}: not a device path nor udpin:/udpout:/tcp:/tcpin:HOST:PORT")
    if comma:
        baud = inline_baud
    baud = 57600 if baud is None else baud
    if isinstance(baud, str) and baud.isdigit():
        baud = int(baud)
    if isinstance(baud, bool) or not isinstance(baud, int) or not hasattr(termios, f"B{baud}"):
        raise ValueError(f"bad baud {baud!r}: not a serial speed this system supports")
    return Address("serial", device=device, baud=baud)


def exclusive_resource(settings: Mapping[str, Any]) -> str | None:
    """What only one open connection can hold: a listening port (``udpin`` -> ``udp:PORT``,
    ``tcpin`` -> ``tcp:PORT``, whatever the host, port 0 excepted) or a serial device
    (``serial:<real path>``: two readers would split the bytes); None for clients and for
    settings :func:`parse_address` rejects (``check`` reports those)."""
    try:
        address = parse_address(settings.get("url"), settings.get("baud"))
    except ValueError:
        return None
    if address.kind in ("udpin", "tcpin") and address.port:
        return f"{'udp' if address.kind == 'udpin' else 'tcp'}:{address.port}"
    if address.kind == "serial":
        return "serial:" + os.path.realpath(address.device)
    return None


def key_files(settings: Mapping[str, Any]) -> list[str]:
    """The signing key file the connection reads when it opens (a reload reopens the
    connection when its contents change)."""
    signing = settings.get("signing")
    if isinstance(signing, Mapping) and isinstance(signing.get("key_file"), str):
        return [str(Path(signing["key_file"]).expanduser())]
    return []


@dataclass(frozen=True, slots=True)
class SigningConfig:
    key: bytes = field(repr=False)
    link_id: int = 0
    timestamp_file: Path | None = None
    allow_unsigned: frozenset[int] = frozenset({RADIO_STATUS})


def load_signing(raw: Any) -> SigningConfig:
    """Read the 32-byte key (raw or 64 hex digits) from ``key_file`` or ``key_env``."""
    if not isinstance(raw, Mapping):
        raise ValueError("signing must be a mapping")
    unknown = set(raw) - _SIGNING
    if unknown:
        raise ValueError(f"unknown signing setting(s): {', '.join(sorted(unknown))}")
    if ("key_file" in raw) == ("key_env" in raw):
        raise ValueError("signing key missing: give exactly one of key_file, key_env")
    if "key_file" in raw:
        path = Path(str(raw["key_file"])).expanduser()
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ValueError(f"signing key missing: cannot read key_file {str(path)!r} ({exc.strerror})") from None
        key = _decode_key(data, f"key_file {str(path)!r}")
    else:
        value = os.environ.get(str(raw["key_env"]))
        if not value:
            raise ValueError(f"signing key missing: environment variable {raw['key_env']!r} is not set")
        key = _decode_key(value.encode(), f"environment variable {raw['key_env']!r}")
    link_id = raw.get("link_id", 0)
    if isinstance(link_id, bool) or not isinstance(link_id, int) or not 0 <= link_id <= 255:
        raise ValueError("signing.link_id must be 0..255")
    stamp = raw.get("timestamp_file")
    stamp_path = Path(str(stamp)).expanduser() if stamp else None
    if stamp_path is not None and not stamp_path.parent.is_dir():
        raise ValueError(f"signing.timestamp_file: directory {str(stamp_path.parent)!r} does not exist")
    allowed = raw.get("allow_unsigned", ["RADIO_STATUS"])
    if not isinstance(allowed, list) or any(name not in MESSAGES for name in allowed):
        raise ValueError("signing.allow_unsigned must be a list of MAVLink message names")
    return SigningConfig(key, link_id, stamp_path, frozenset(MESSAGES[name].id for name in allowed))


def _decode_key(data: bytes, where: str) -> bytes:
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        with contextlib.suppress(ValueError):
            return bytes.fromhex(text.decode("ascii", "replace"))
    if len(text) == 32:
        return text
    raise ValueError(f"signing key in {where} must be 32 bytes or 64 hex digits")


@dataclass(frozen=True, slots=True)
class LinkConfig:
    address: Address
    source_system: int = 255
    source_component: int = 190
    signing: SigningConfig | None = None
    rate: float = 0.0
    heartbeat: float = 1.0
    mav_type: int = mavlink2.MAV_TYPE_GCS
    tunnel: TunnelSettings = field(default_factory=TunnelSettings)

    @property
    def bulk_rate(self) -> float:
        if self.tunnel.rate:
            return self.tunnel.rate
        return self.rate / 2 if self.address.kind == "serial" else 0.0


def settings_problems(settings: Mapping[str, Any]) -> tuple[LinkConfig | None, list[tuple[str | None, str]]]:
    """Parse connection settings, collecting every problem with the key it belongs to."""
    problems: list[tuple[str | None, str]] = []
    for key in sorted(set(settings) - _SETTINGS):
        problems.append((key, f"unknown setting {key!r}"))
    address = None
    try:
        address = parse_address(settings.get("url"), settings.get("baud"))
    except ValueError as exc:
        problems.append(("baud" if "baud" in str(exc) else "url", str(exc)))
    values: dict[str, Any] = {}
    for key, low, high in (("source_system", 1, 255), ("source_component", 0, 255), ("mav_type", 0, 255)):
        if key in settings:
            value = settings[key]
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                problems.append((key, f"{key} must be an integer {low}..{high}"))
            else:
                values[key] = value
    for key in ("rate", "heartbeat"):
        if key in settings:
            value = settings[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0 or not math.isfinite(value):
                problems.append((key, f"{key} must be a non-negative number"))
            else:
                values[key] = float(value)
    if settings.get("signing") is not None:
        try:
            values["signing"] = load_signing(settings["signing"])
        except ValueError as exc:
            problems.append(("signing", str(exc)))
    if address is not None:
        try:
            values["tunnel"] = TunnelSettings.from_settings(settings.get("tunnel"), serial=address.kind == "serial")
        except ValueError as exc:
            problems.append(("tunnel", str(exc)))
        if "rate" not in values and address.kind == "serial":
            values["rate"] = address.baud / 10
    if problems or address is None:
        return None, problems
    return LinkConfig(address, **values), problems

