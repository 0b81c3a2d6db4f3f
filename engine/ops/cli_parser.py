"""The ``rabbitros-engine`` command line: its commands and their options (engine/ops/cli.py runs them).

Apart from cli.py because the options are a long table that changes with every feature, while
what the commands do changes with the engine; the CLI tests read the table from here.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import NoReturn

from engine import __version__, endpoints
from engine.ops.admin import parse_address
from engine.ops.replay_sinks import parse_speed
from engine.ops.supervisor import worker_count

_Commands = argparse._SubParsersAction  # what add_subparsers returns: each command is added to it

COMMANDS = ("run", "check", "test", "replay", "status", "tap", "dead-letters")


class _TopLevelParser(argparse.ArgumentParser):
    """``rabbitros-engine --help`` shows how to run, not only the commands: ``run`` is the
    default command, so its options follow the command list."""

    run_parser: argparse.ArgumentParser | None = None

    def error(self, message: str) -> NoReturn:
        """argparse's error, with the way to give a routes directory when a bare word was one
        (``check --workers 2 examples/``: the directory is an option's value, not a word)."""
        if message.startswith("unrecognized arguments:") and any(Path(word).exists() for word in message.split(":", 1)[1].split()):
            message += " (give the routes directory as --routes DIR)"
        super().error(message)

    def format_help(self) -> str:
        text = super().format_help()
        if self.run_parser is None:
            return text
        formatter = self.run_parser._get_formatter()
        formatter.start_section("run options (run is the default command: rabbitros-engine [run] [OPTIONS])")
        formatter.add_arguments([a for a in self.run_parser._actions if not isinstance(a, argparse._HelpAction)])
        formatter.end_section()
        formatter.add_text("Example: rabbitros-engine --routes routes/ --local-broker --admin 9180. "
                           "Each command's own options: rabbitros-engine COMMAND --help.")
        return text + "\n" + formatter.format_help()


def build_parser() -> argparse.ArgumentParser:
    """The command line: one function a command below, so each command's options read together."""
    parser = _TopLevelParser(
        prog="rabbitros-engine",
        usage="%(prog)s [run] [--routes DIR] [--local-broker] [--admin [HOST:]PORT] [OPTIONS]\n"
              "       %(prog)s {check,test,status,tap,dead-letters} ...",
        description="Routes messages between " + ", ".join(endpoints.PROTOCOLS) + " endpoints as declared in YAML route files.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="{run,check,test,replay,status,tap,dead-letters}", title="commands")
    parser.run_parser = _add_run(commands)
    _add_check(commands)
    _add_test(commands)
    _add_replay(commands)
    _add_status(commands)
    _add_tap(commands)
    _add_dead_letters(commands)
    return parser


def _routes_options(sub: argparse.ArgumentParser) -> None:
    """--routes and --schemas, which every command reading route files takes."""
    sub.add_argument("--routes", type=Path, default=Path("routes"), metavar="DIR", help="routes directory (or one file); default ./routes")
    sub.add_argument("--schemas", type=Path, action="append", metavar="DIR",
                     help="canonical schemas directory; default: schemas/ beside the routes. May repeat: a later "
                          "directory over the earlier (a file of the same name replaces the earlier's), e.g. the "
                          "bundled schemas, then your own")


def _add_run(commands: _Commands) -> argparse.ArgumentParser:
    """``run``: the engine's options (the default command)."""
    run = commands.add_parser("run", help="run the routes (the default command)")
    _routes_options(run)
    run.add_argument("--local-broker", action="store_true", help="start the private broker of each protocol that has one and use it as that protocol's default connection")
    run.add_argument("--broker-url-file", type=Path, metavar="FILE", help="with --local-broker: write the brokers' URLs to this file, one a line")
    run.add_argument("--cluster", type=int, default=1, metavar="N",
                     help="with --local-broker: start N nodes of each broker joined in one cluster (default 1); the default connection lists them all")
    run.add_argument("--local-broker-tls", action="store_true",
                     help="with --local-broker: the private broker listens with TLS, its certificate from a CA made for the run; the default connection verifies against it")
    run.add_argument("--status-file", type=Path, metavar="FILE", help="keep the live status (generation, config hash, counters) in this JSON file")
    run.add_argument("--admin", type=_admin_address, metavar="[HOST:]PORT",
                     help="serve /metrics, /healthz, /status and /tap/ROUTE over HTTP (a bare port binds 127.0.0.1); off by default")
    run.add_argument("--admin-token-file", type=Path, metavar="FILE",
                     help="a bearer token every admin path but /healthz asks for; required when --admin is not a loopback address")
    run.add_argument("--admin-tls-cert", type=Path, metavar="FILE", help="serve the admin endpoint over HTTPS with this certificate (PEM)")
    run.add_argument("--admin-tls-key", type=Path, metavar="FILE", help="the private key of --admin-tls-cert (PEM)")
    run.add_argument("--foxglove", type=_admin_address, metavar="[HOST:]PORT",
                     help="serve a read-only live view to Foxglove or Lichtblick (ws://HOST:PORT): each route's canonical "
                          "messages, the fleet on a map and the routes' status (a bare port binds 127.0.0.1); off by default")
    run.add_argument("--foxglove-tls-cert", type=Path, metavar="FILE", help="serve the Foxglove view over wss:// with this certificate (PEM)")
    run.add_argument("--foxglove-tls-key", type=Path, metavar="FILE", help="the private key of --foxglove-tls-cert (PEM, PKCS#8)")
    run.add_argument("--instance", metavar="NAME", help="this engine's name among instances sharing the routes (routes' instances:); default the host name")
    run.add_argument("--no-watch", action="store_true", help="do not reload when route files change (SIGHUP still reloads)")
    run.add_argument("--test-on-reload", action="store_true",
                     help="run the directory's route tests (*.test.yaml) on every load and reload first, and refuse a "
                          "generation whose tests fail as a syntax error is refused: the running routes keep running")
    run.add_argument("--stats-interval", type=float, default=10.0, metavar="SECONDS",
                     help="seconds between status-file updates and the log's route counter lines; default 10")
    run.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"], help="default info")
    run.add_argument("--log-format", default="text", choices=["text", "json"],
                     help="text lines, or one JSON object per line (for a log collector); default text")
    run.add_argument("--require-connections", action="store_true", help="exit 1 when a connection cannot be opened at start (default: retry it in the background while the other routes run)")
    run.add_argument("--record", type=Path, metavar="DIR",
                     help="record what every route receives and the canonical messages it sends in MCAP files in DIR "
                          "(routes with record: false left out; docs/operations.md)")
    run.add_argument("--record-file-mb", type=float, default=256.0, metavar="MB", help="with --record: start a new file past this size; default 256")
    run.add_argument("--record-file-minutes", type=float, default=60.0, metavar="MINUTES",
                     help="with --record: start a new file once one is this old; default 60")
    run.add_argument("--record-total-mb", type=float, default=4096.0, metavar="MB",
                     help="with --record: remove the oldest files while the recordings exceed this; default 4096")
    run.add_argument("--drain-timeout", type=float, default=10.0, metavar="SECONDS", help="seconds a stop (SIGTERM, SIGINT) waits for in-flight messages before requeueing the rest; default 10")
    run.add_argument("--workers", type=worker_count, default=1, metavar="N|auto",
                     help="run N engine processes under one supervisor and one admin endpoint (auto: one per core); "
                          "a broker queue is consumed by every worker, a device or a link by one (check --workers N shows where)")
    run.add_argument("--worker", type=int, help=argparse.SUPPRESS)  # set by the supervisor: this process is worker K of --workers
    run.add_argument("--worker-channel", type=int, help=argparse.SUPPRESS)  # the pipe a worker says it runs on
    run.add_argument("--supervisor-pid", type=int, help=argparse.SUPPRESS)  # a worker stops when its parent is not this
    run.add_argument("--runtime-dir", help=argparse.SUPPRESS)  # the supervisor's private directory (split connections' sockets)
    return run


def _add_check(commands: _Commands) -> None:
    """``check``: validate without connecting."""
    check = commands.add_parser("check", help="validate the routes (and their *.test.yaml files) without connecting; exit 0 when valid")
    _routes_options(check)
    check.add_argument("--local-broker", action="store_true",
                       help="check as run --local-broker would load the routes: warn about connections that name another broker")
    check.add_argument("--workers", type=worker_count, default=1, metavar="N|auto", help="print on which worker of run --workers N each route runs")


def _add_test(commands: _Commands) -> None:
    """``test``: the route tests, or tests made from a recording."""
    test = commands.add_parser(
        "test", help="run the *.test.yaml cases through the routes' conversion, connecting to nothing; "
        "exit 0 when all pass, 1 when one fails, 2 when a route or test file is invalid")
    _routes_options(test)
    test.add_argument("--from-recording", nargs="+", type=Path, metavar="FILE",
                      help="instead of running the tests, print route tests (a *.test.yaml) made from a recording (--record): "
                           "the first --count inputs of --route that were sent, each expecting its recorded canonical message")
    test.add_argument("--route", metavar="NAME", help="with --from-recording: the route")
    test.add_argument("--count", type=int, default=20, metavar="N", help="with --from-recording: at most N cases; default 20")


def _add_replay(commands: _Commands) -> None:
    """``replay``: a recording through the routes as they are now."""
    replay = commands.add_parser(
        "replay", help="convert the inputs of a recording (--record) through the routes as they are now and compare each "
        "canonical message with the recorded one; connects to nothing; exit 0 when none differs, 1 when one does, 2 when invalid")
    replay.add_argument("recording", nargs="+", type=Path, metavar="FILE", help="MCAP files of --record (a directory: all its recordings)")
    _routes_options(replay)
    replay.add_argument("--route", metavar="NAME", help="replay this route only")
    replay.add_argument("--ignore", action="append", default=[], metavar="KEY",
                        help="leave this key (a.b) of the canonical messages out of the comparison, e.g. what a mapping takes "
                             "from the clock (stamp()); repeatable")
    replay.add_argument("--to-sinks", action="store_true",
                        help="instead of comparing, send the recorded inputs through the routes as they are now to their real "
                             "sinks, in the order received; exit 1 when one was not sent")
    replay.add_argument("--speed", type=_speed, default=1.0, metavar="N|max",
                        help="with --to-sinks: 1 = the recorded pace (default), 10 = ten times faster, max = as fast as the sinks take them")


def _add_status(commands: _Commands) -> None:
    """``status``: a running engine's status."""
    status = commands.add_parser("status", help="the live status of a running engine: a table from its admin endpoint, or the JSON of its status file")
    where = status.add_mutually_exclusive_group(required=True)
    where.add_argument("--admin", type=_admin_address, metavar="[HOST:]PORT", help="the engine's --admin address")
    where.add_argument("--status-file", type=Path, help="the engine's --status-file (printed as JSON)")
    status.add_argument("--json", action="store_true", help="print the raw status document")
    _client_access_options(status)


def _add_tap(commands: _Commands) -> None:
    """``tap``: a route's messages as JSON lines."""
    tap = commands.add_parser("tap", help="print, as JSON lines, every message through a route of a running engine; "
                              "stderr says 'listening' once it is attached, exit 1 when the engine goes away")
    tap.add_argument("route")
    tap.add_argument("--admin", type=_admin_address, metavar="[HOST:]PORT", required=True, help="the engine's --admin address")
    tap.add_argument("--count", type=int, default=0, help="stop after this many messages (default: until interrupted)")
    _client_access_options(tap)


def _add_dead_letters(commands: _Commands) -> None:
    """``dead-letters``: list, show or replay the stored dead letters."""
    dead = commands.add_parser("dead-letters", help="list, show or replay the dead letters the routes' engine stored (its "
                               "dead-letter queue and local spool); replay sends them into their routes as they are now")
    actions = dead.add_subparsers(dest="action", metavar="{list,show,replay}", required=True)
    for action, text in (("list", "one line a dead letter: id, when stored, route, stage, error"),
                         ("show", "each dead letter as a JSON line: headers and body"),
                         ("replay", "send each through its route's conversion and sink as the route files say now; removed "
                                    "from its store only once the sink accepted it; exit 1 when some are kept")):
        sub = actions.add_parser(action, help=text)
        _routes_options(sub)
        sub.add_argument("--route", action="append", metavar="NAME", help="only this route's (repeat for several)")
        sub.add_argument("--stage", action="append", metavar="STAGE", help="only those of this stage: decode, mapping, schema, "
                                                                           "when, sink mapping, sink, size... (repeat for several)")
        sub.add_argument("--id", action="append", metavar="ID", help="only this letter (the id list prints; repeat for several)")
        sub.add_argument("--since", metavar="TIME", help="stored at or after TIME: 2026-11-27T14:00:00 (UTC unless it says), or ago: 30m, 2h, 1d")
        sub.add_argument("--until", metavar="TIME", help="stored at or before TIME (as --since)")
        sub.add_argument("--limit", type=int, default=10_000, metavar="N", help="read at most N from each store (default 10000)")
        if action == "replay":
            sub.add_argument("--ready-timeout", type=float, default=10.0, metavar="SECONDS",
                             help="how long to wait for a sink that cannot take messages yet (a topic no reader matched yet); default 10")


def _client_access_options(sub: argparse.ArgumentParser) -> None:
    sub.add_argument("--admin-token-file", type=Path, metavar="FILE", help="the engine's --admin-token-file (sent as a bearer token)")
    sub.add_argument("--admin-ca-file", type=Path, metavar="FILE",
                     help="speak HTTPS to the admin endpoint and verify its certificate with this CA (PEM)")


def _speed(text: str) -> float | None:
    try:
        return parse_speed(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _admin_address(text: str) -> tuple[str, int]:
    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
