"""Operator views of a running engine through its admin endpoint: the status table and the tap.

``rabbitros-engine status --admin PORT`` and the farm demo's live view render the same
table (rich), so what an operator sees in the field is what the demo shows. Plain stdlib
HTTP (urllib) is enough for one request or one stream, and keeps these commands free of
an event loop.
"""

from __future__ import annotations

import json
import sys
import time
import urllib.error
import urllib.request
from typing import Any

from rich.console import Console, Group
from rich.table import Table
from rich.text import Text


def admin_url(address: tuple[str, int], path: str) -> str:
    host, port = address
    return f"http://{f'[{host}]' if ':' in host else host}:{port}{path}"


def fetch_status(address: tuple[str, int], timeout: float = 5.0) -> dict[str, Any]:
    with urllib.request.urlopen(admin_url(address, "/status"), timeout=timeout) as response:
        return json.loads(response.read())


def _count(value: Any) -> str:
    return f"{value:,}" if isinstance(value, int) else "-"


def _rate(value: Any) -> str:
    return f"{value:.1f}" if isinstance(value, (int, float)) else "-"


def _age(at: Any, now: float) -> str:
    if not isinstance(at, (int, float)):
        return ""
    seconds = max(0.0, now - at)
    return f"{seconds:.0f}s ago" if seconds < 120 else f"{seconds / 60:.0f}m ago"


def status_table(status: dict[str, Any], last_canonical: bool = False, width: int = 60) -> Group:
    """The status document as a rich table (and a header line)."""
    now = time.time()
    connections = status.get("connections", {})
    down = [name for name, c in connections.items() if not c.get("up", True)]
    reloads = status.get("reloads", {})
    header = Text.assemble(
        ("generation ", "dim"), str(status.get("generation")), ("  config ", "dim"), str(status.get("config_hash")),
        ("  reloads ", "dim"), f"{reloads.get('succeeded', 0)} ok / {reloads.get('rejected', 0)} rejected",
        ("  connections ", "dim"),
        (f"{len(connections) - len(down)}/{len(connections)} up", "red" if down else "green"),
        (f" (down: {', '.join(down)})" if down else "", "red"),
    )
    rejected = [f"{name}: " + ", ".join(f"{key} {count}" for key, count in c["rejected"].items() if count)
                for name, c in connections.items() if any((c.get("rejected") or {}).values())]
    if rejected:
        header.append(Text.assemble(("\nlink rejections ", "dim"), ("; ".join(rejected), "yellow")))
    table = Table(expand=False, header_style="bold")
    for column, justify in (("route", "left"), ("state", "left"), ("recv/s", "right"), ("sent/s", "right"),
                            ("received", "right"), ("delivered", "right"), ("dead", "right"),
                            ("redelivered", "right"), ("conflated", "right"), ("dropped", "right"),
                            ("last error", "left")):
        table.add_column(column, justify=justify, no_wrap=True, overflow="ellipsis",
                         max_width=width if column == "last error" else None)
    if last_canonical:
        table.add_column("last canonical message", overflow="ellipsis", no_wrap=True, max_width=width)
    for name, route in status.get("routes", {}).items():
        messages = route.get("messages") or {}
        state = route.get("state", "running")
        error = route.get("last_error") or ""
        if error:
            error = f"{error[:80]} ({_age(route.get('last_error_at'), now)})"
        holding = route.get("sink_not_ready")
        if holding and state == "running":  # the sink cannot take messages yet: say why
            state, error = "holding", error or holding
        row = [name, Text(state, "green" if state == "running" else "yellow"),
               _rate(route.get("received_per_s")), _rate(route.get("delivered_per_s")),
               _count(messages.get("received")), _count(messages.get("delivered")),
               _count(messages.get("dead_lettered")), _count(messages.get("redelivered")),
               _count(messages.get("conflated")), _count(route.get("dropped")), Text(error, "red")]
        if last_canonical:
            last = route.get("last_canonical")
            row.append("" if last is None else json.dumps(last, separators=(",", ":"), default=str))
        table.add_row(*row)
    return Group(header, table)


def print_status(address: tuple[str, int], raw: bool) -> int:
    try:
        status = fetch_status(address)
    except (OSError, urllib.error.URLError, ValueError) as exc:
        print(f"{admin_url(address, '/status')}: {getattr(exc, 'reason', exc)}", file=sys.stderr)
        return 1
    if raw:
        print(json.dumps(status, indent=2))
        return 0
    Console(width=None if sys.stdout.isatty() else 200).print(status_table(status))
    return 0


def print_tap(address: tuple[str, int], route: str, count: int) -> int:
    """Print the tap's JSON lines as they come; ``count`` > 0 stops after that many."""
    url = admin_url(address, f"/tap/{urllib.request.quote(route, safe='')}")
    seen = 0
    try:
        with urllib.request.urlopen(url, timeout=None) as response:
            for line in response:
                sys.stdout.write(line.decode("utf-8"))
                sys.stdout.flush()
                seen += 1
                if count and seen >= count:
                    break
    except urllib.error.HTTPError as exc:
        detail = exc.read().decode("utf-8", errors="replace")
        try:
            detail = json.loads(detail)["error"]
        except (ValueError, KeyError, TypeError):
            pass
        print(f"{url}: {exc.code}: {detail}", file=sys.stderr)
        return 1
    except (OSError, urllib.error.URLError) as exc:
        print(f"{url}: {getattr(exc, 'reason', exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    return 0
