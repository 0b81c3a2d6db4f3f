"""Connection settings (YAML ``connections.<name>.mavlink``), parsed once into a typed value.

Every problem is collected with the key it belongs to, so ``check`` names the file, route and
field; the connection itself is built from the resulting :class:`LinkConfig`.
"""

from __future__ import annotations

import contextlib
import os
import termios
from datetime import datetime
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from engine.endpoints.base import typed_or_problem
from engine.endpoints.mavlink.codec import MESSAGES, RADIO_STATUS, mavlink2
from engine.endpoints.mavlink.options import MavlinkConnectionOptions, MavlinkSigning
from engine.endpoints.mavlink.tunnel import TunnelSettings


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


def exclusive_resource(settings: MavlinkConnectionOptions) -> str | None:
    """What only one open connection can hold: a listening port (``udpin`` -> ``udp:PORT``,
    ``tcpin`` -> ``tcp:PORT``, whatever the host, port 0 excepted) or a serial device
    (``serial:<real path>``: two readers would split the bytes); None for clients and for
    settings :func:`parse_address` rejects (``check`` reports those)."""
    try:
        address = parse_address(settings.url, settings.baud)
    except ValueError:
        return None
    if address.kind in ("udpin", "tcpin") and address.port:
        return f"{'udp' if address.kind == 'udpin' else 'tcp'}:{address.port}"
    if address.kind == "serial":
        return "serial:" + os.path.realpath(address.device)
    return None


def key_files(settings: MavlinkConnectionOptions) -> list[str]:
    """The signing key file the connection reads when it opens (a reload reopens the
    connection when its contents change)."""
    signing = settings.signing
    if signing is None:
        return []
    names = [signing.key_file] if signing.key_file is not None else []
    return [str(Path(name).expanduser()) for name in [*names, *(old.key_file for old in signing.accept)]]


@dataclass(frozen=True, slots=True)
class SigningConfig:
    key: bytes = field(repr=False)
    link_id: int = 0
    timestamp_file: Path | None = None
    allow_unsigned: frozenset[int] = frozenset({RADIO_STATUS})
    accepted: tuple[tuple[bytes, float], ...] = field(default=(), repr=False)
    """Old keys still accepted on incoming frames, each with its deadline (Unix time)."""


def load_signing(raw: MavlinkSigning) -> SigningConfig:
    """Read the 32-byte key (raw or 64 hex digits) from ``key_file`` or ``key_env``."""
    if (raw.key_file is None) == (raw.key_env is None):
        raise ValueError("signing key missing: give exactly one of key_file, key_env")
    if raw.key_file is not None:
        path = Path(raw.key_file).expanduser()
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ValueError(f"signing key missing: cannot read key_file {str(path)!r} ({exc.strerror})") from None
        key = _decode_key(data, f"key_file {str(path)!r}")
    else:
        value = os.environ.get(str(raw.key_env))
        if not value:
            raise ValueError(f"signing key missing: environment variable {raw.key_env!r} is not set")
        key = _decode_key(value.encode(), f"environment variable {raw.key_env!r}")
    stamp_path = Path(raw.timestamp_file).expanduser() if raw.timestamp_file else None
    if stamp_path is not None and not stamp_path.parent.is_dir():
        raise ValueError(f"signing.timestamp_file: directory {str(stamp_path.parent)!r} does not exist")
    if any(name not in MESSAGES for name in raw.allow_unsigned):
        raise ValueError("signing.allow_unsigned must be a list of MAVLink message names")
    accepted = tuple((_read_key_file(old.key_file), _deadline(old.until)) for old in raw.accept)
    return SigningConfig(key, raw.link_id, stamp_path, frozenset(MESSAGES[name].id for name in raw.allow_unsigned), accepted)


def _read_key_file(name: str) -> bytes:
    path = Path(name).expanduser()
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"signing key missing: cannot read key_file {str(path)!r} ({exc.strerror})") from None
    return _decode_key(data, f"key_file {str(path)!r}")


def _deadline(text: str) -> float:
    """``until`` as Unix time; a time without a zone is refused (a fleet spans time zones)."""
    try:
        moment = datetime.fromisoformat(text.replace("Z", "+00:00") if text.endswith("Z") else text)
    except ValueError:
        raise ValueError(f"signing.accept until {text!r} is not an ISO 8601 time (2026-12-01T00:00:00Z)") from None
    if moment.tzinfo is None:
        raise ValueError(f"signing.accept until {text!r} has no time zone (add Z for UTC)")
    return moment.timestamp()


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
    budget: float | None = None
    heartbeat_timeout: float = 3.0
    """Seconds without a HEARTBEAT after which a vehicle is down (connection.py)."""
    split_over_workers: bool = False
    """Under ``run --workers N``, the vehicles are split over the workers by system id (split.py)."""

    @property
    def bulk_rate(self) -> float:
        """The ceiling of the routes' budget (engine/endpoints/mavlink/budget.py), bytes/s; 0: unpaced."""
        if self.budget:
            return self.budget
        if self.tunnel.rate:
            return self.tunnel.rate
        return self.rate / 2 if self.address.kind == "serial" else 0.0


def settings_problems(
    settings: MavlinkConnectionOptions | Mapping[str, Any],
) -> tuple[LinkConfig | None, list[tuple[str | None, str]]]:
    """Resolve connection settings into a :class:`LinkConfig`, collecting every problem with
    the key it belongs to (the address, the signing key, the tunnel's timing)."""
    options, problems = typed_or_problem(MavlinkConnectionOptions, settings)
    if options is None:
        return None, problems
    address = None
    try:
        address = parse_address(options.url, options.baud)
    except ValueError as exc:
        problems.append(("baud" if "baud" in str(exc) else "url", str(exc)))
    signing = None
    if options.signing is not None:
        try:
            signing = load_signing(options.signing)
        except ValueError as exc:
            problems.append(("signing", str(exc)))
    if address is None:
        return None, problems
    try:
        tunnel = TunnelSettings.from_settings(options.tunnel, serial=address.kind == "serial")
    except ValueError as exc:
        problems.append(("tunnel", str(exc)))
    if options.split_over_workers and address.kind != "udpin":
        problems.append(("split_over_workers", f"split_over_workers applies to udpin links only (vehicles told apart by "
                                               f"their UDP source), not {address.kind}"))
    if options.split_over_workers and options.signing is not None:
        problems.append(("split_over_workers", "split_over_workers is not built for signed links: the worker holding the "
                                               "socket would hand frames on by headers it has not verified"))
    if problems:
        return None, problems
    rate = options.rate if options.rate is not None else (address.baud / 10 if address.kind == "serial" else 0.0)
    return LinkConfig(address, options.source_system, options.source_component, signing, float(rate),
                      float(options.heartbeat), options.mav_type, tunnel, options.budget,
                      float(options.heartbeat_timeout), options.split_over_workers), problems
