"""Operator views of a running engine through its admin endpoint: the status table and the tap.

``rabbitros-engine status --admin PORT`` and the farm demo's live view render the same
table (rich), so what an operator sees in the field is what the demo shows. Plain stdlib
HTTP (urllib) is enough for one request or one stream, and keeps these commands free of
an event loop.
"""

from __future__ import annotations

import http.client
import json
import ssl
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console, Group, JustifyMethod
from rich.table import Table
from rich.text import Text


@dataclass(frozen=True)
class AdminClient:
    """How a command reaches an admin endpoint: the bearer token it sends (``status``/``tap
    --admin-token-file``) and, for HTTPS, the context verifying the engine's certificate
    against ``--admin-ca-file``."""

    token: str | None = None
    tls: ssl.SSLContext | None = None

    @classmethod
    def from_files(cls, address: tuple[str, int], token_file: Path | None, ca_file: Path | None) -> AdminClient:
        from engine.ops.admin import AdminConfigError, read_token

        tls = None
        if ca_file is not None:
            try:
                tls = ssl.create_default_context(cafile=str(ca_file))
            except (OSError, ssl.SSLError) as exc:
                raise AdminConfigError(f"--admin-ca-file {ca_file}: {getattr(exc, 'strerror', None) or exc}") from None
        return cls(read_token(token_file).decode() if token_file is not None else None, tls)

    def open(self, address: tuple[str, int], path: str, timeout: float | None) -> Any:
        request = urllib.request.Request(admin_url(address, path, self))
        if self.token is not None:
            request.add_header("Authorization", f"Bearer {self.token}")
        return urllib.request.urlopen(request, timeout=timeout, context=self.tls)


def admin_url(address: tuple[str, int], path: str, client: AdminClient | None = None) -> str:
    host, port = address
    scheme = "https" if client is not None and client.tls is not None else "http"
    return f"{scheme}://{f'[{host}]' if ':' in host else host}:{port}{path}"


def fetch_status(address: tuple[str, int], timeout: float = 5.0, client: AdminClient | None = None) -> dict[str, Any]:
    with (client or AdminClient()).open(address, "/status", timeout) as response:
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


SHOWN_PROBLEMS = 5
"""Problems of a rejected reload the table shows; ``status --json`` has every one."""


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
    workers = status.get("workers") or []
    if workers:  # run --workers N: the supervisor's document (engine/ops/supervisor_admin.py)
        up = sum(1 for w in workers if w.get("up"))
        header.append(Text.assemble(("\nworkers ", "dim"), (f"{up}/{len(workers)} up", "green" if up == len(workers) else "red"), *(
            (f"  {w['index']}: pid {w['pid']}, {len(w.get('routes', []))} routes, restarts {w['restarts']}"
             + (f", cpu {w['cpu_s']} s, rss {w['rss_mib']} MiB" if "cpu_s" in w else ""), "dim") for w in workers)))
    rejected = [f"{name}: " + ", ".join(f"{key} {count}" for key, count in c["rejected"].items() if count)
                for name, c in connections.items() if any((c.get("rejected") or {}).values())]
    if rejected:
        header.append(Text.assemble(("\nlink rejections ", "dim"), ("; ".join(rejected), "yellow")))
    table = Table(expand=False, header_style="bold")
    columns: tuple[tuple[str, JustifyMethod], ...] = (
        ("route", "left"), ("state", "left"), ("recv/s", "right"), ("sent/s", "right"),
        ("received", "right"), ("delivered", "right"), ("refused", "right"), ("dead", "right"),
        ("redelivered", "right"), ("conflated", "right"), ("expired", "right"), ("filtered", "right"),
        ("dup", "right"), ("dropped", "right"),
        ("last error", "left"))
    for column, justify in columns:
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
        degraded = route.get("source_degraded")
        if degraded and state == "running":  # the source receives nothing (the broker cancelled it): say why
            state, error = "degraded", degraded
        row = [name, Text(state, "green" if state == "running" else "yellow"),
               _rate(route.get("received_per_s")), _rate(route.get("delivered_per_s")),
               _count(messages.get("received")), _count(messages.get("delivered")), _count(messages.get("refused")),
               _count(messages.get("dead_lettered")), _count(messages.get("redelivered")),
               _count(messages.get("conflated")), _count(messages.get("expired")), _count(messages.get("filtered")),
               _count(messages.get("duplicates")), _count(route.get("dropped")), Text(error, "red")]
        if last_canonical:
            last = route.get("last_canonical")
            row.append("" if last is None else json.dumps(last, separators=(",", ":"), default=str))
        table.add_row(*row)
    return Group(header, *_rejected_reload(status), table)


def _rejected_reload(status: dict[str, Any]) -> list[Text]:
    """The last rejected reload's problems, ``file:line: message`` each on a line of its own
    (``print_status`` never wraps them: an operator greps or copies them); nothing once a later
    reload applied or the files are back to what runs."""
    problems = (status.get("reloads") or {}).get("last_error") or []
    if not problems:
        return []
    lines = [Text.assemble(("last reload rejected", "red"), (f" (generation {status.get('generation')} keeps running):", "dim"))]
    lines += [Text(f"  {problem}", "red") for problem in problems[:SHOWN_PROBLEMS]]
    if len(problems) > SHOWN_PROBLEMS:
        lines.append(Text(f"  ... and {len(problems) - SHOWN_PROBLEMS} more (status --json lists them all)", "dim"))
    return lines


def print_status(address: tuple[str, int], raw: bool, client: AdminClient | None = None) -> int:
    try:
        status = fetch_status(address, client=client)
    except urllib.error.HTTPError as exc:
        print(f"{admin_url(address, '/status', client)}: {exc.code} {exc.reason}{_token_hint(exc.code, client)}", file=sys.stderr)
        return 1
    except (OSError, urllib.error.URLError, ValueError) as exc:
        print(f"{admin_url(address, '/status', client)}: {getattr(exc, 'reason', exc)}", file=sys.stderr)
        return 1
    if raw:
        print(json.dumps(status, indent=2))
        return 0
    # soft_wrap: the header's lines (a rejected reload's file:line: message) are never wrapped or cut
    Console(width=None if sys.stdout.isatty() else 200).print(status_table(status), soft_wrap=True)
    return 0


def _token_hint(code: int, client: AdminClient | None) -> str:
    if code != 401:
        return ""
    return " (the engine asks for a token: --admin-token-file)" if client is None or client.token is None else " (wrong token)"


def print_tap(address: tuple[str, int], route: str, count: int, client: AdminClient | None = None) -> int:
    """Print the tap's JSON lines (stdout) as they come; ``count`` > 0 stops after that many.

    Once the engine has attached the tap (it does so before answering), a line on stderr says
    so: a script can wait for ``listening`` and then publish, without losing the first
    messages. The stream ends only when the engine stops (or its admin endpoint does), so an
    end before ``count`` lines, or a connection lost, is an error (exit 1) that says so."""
    path = f"/tap/{urllib.parse.quote(route, safe='')}"
    url = admin_url(address, path, client)
    seen = 0
    try:
        with (client or AdminClient()).open(address, path, None) as response:
            print(f"tap {route}: listening on {url}" + (f" for {count} messages" if count else " (Ctrl-C stops)"),
                  file=sys.stderr, flush=True)
            for line in response:
                sys.stdout.write(line.decode("utf-8"))
                sys.stdout.flush()
                seen += 1
                if count and seen >= count:
                    return 0
    except urllib.error.HTTPError as exc:
        detail = exc.read().decode("utf-8", errors="replace")
        try:
            detail = json.loads(detail)["error"]
        except (ValueError, KeyError, TypeError):
            pass
        print(f"{url}: {exc.code}: {detail}{_token_hint(exc.code, client)}", file=sys.stderr)
        return 1
    except urllib.error.URLError as exc:
        print(f"tap {route}: cannot reach the engine's admin endpoint at {url}: {exc.reason} "
              "(is the engine running with --admin on that port?)", file=sys.stderr)
        return 1
    except (OSError, http.client.HTTPException) as exc:
        print(f"tap {route}: lost the engine at {url} after {seen} messages: {_reason(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    print(f"tap {route}: the engine went away after {seen} messages (it stopped or was killed; "
          f"the tap ends with it)", file=sys.stderr)
    return 1


def _reason(exc: BaseException) -> str:
    if isinstance(exc, http.client.IncompleteRead):
        return "the connection closed mid-message (the engine died?)"
    return str(exc) or type(exc).__name__
