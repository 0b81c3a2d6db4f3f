"""A consumer of one RabbitMQ queue that costs its machine as little as a Python process can:
the fleet benchmark's stand-in for the supervisory software at the far end (bench/fleet.py).

Why not aiormq: in bench/fleet.py the consumer shares the 2 cores with what it measures, and
aiormq's consumer (pamqp's frame parser, a message object and a task per delivery) took 0.32
of a core for 2,000 messages/s: the second-largest user of the machine after the bridge
itself, so the machine ran at ~86 % busy and every process's tail latency with it. Here the
handshake is pamqp's (frames built and read by the library), and the deliveries are read with
one ``recv`` per socket read and ``struct`` at fixed offsets; no ack (``no_ack``) and no
heartbeat (0 is asked, so the broker sends none). Each message is stamped with the wall clock
at the ``recv`` that completed it: the time the bytes reached this process, not when a loop got
round to them.

Only what a consume needs is read: Basic.Deliver, its content header and body frames, and a
Connection.Close or Channel.Close (raised with the broker's text)."""

from __future__ import annotations

import socket
import struct
import time
from typing import Callable, TypeVar
from urllib.parse import unquote, urlparse

from pamqp import commands, frame, header

FRAME_END = 0xCE
_HEAD = struct.Struct(">BHI")
_METHOD = struct.Struct(">HH")
_BODY_SIZE = struct.Struct(">Q")
DELIVER = (60, 60)
CLOSES = {(10, 50): "connection", (20, 40): "channel"}
Arrival = tuple[int, str, bytes]
"""(wall-clock ns at arrival, routing key, body)"""
_Frame = TypeVar("_Frame", bound=frame.FrameTypes)


class _Message:
    """The delivery being read: its routing key, body size and the body so far."""

    __slots__ = ("key", "size", "body")

    def __init__(self) -> None:
        self.key, self.size, self.body = "", 0, bytearray()


class BrokerClosed(RuntimeError):
    """The broker closed the connection or the channel; the message gives its reply text."""


class QueueReader:
    """One connection, one channel, one queue declared exclusive and bound as asked."""

    def __init__(self, url: str) -> None:
        parts = urlparse(url)
        self._sock = socket.create_connection((parts.hostname or "localhost", parts.port or 5672), timeout=30)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buffer = bytearray()
        self._sock.sendall(header.ProtocolHeader().marshal())
        self._expect(commands.Connection.Start)
        user, password = unquote(parts.username or "guest"), unquote(parts.password or "guest")
        self._send(0, commands.Connection.StartOk(client_properties={"product": "bench.amqp_reader"},
                                                  response=f"\0{user}\0{password}"))
        tune = self._expect(commands.Connection.Tune)
        self._send(0, commands.Connection.TuneOk(channel_max=1, frame_max=tune.frame_max, heartbeat=0))
        self._send(0, commands.Connection.Open(virtual_host=unquote(parts.path[1:]) or "/"))
        self._expect(commands.Connection.OpenOk)
        self._send(1, commands.Channel.Open())
        self._expect(commands.Channel.OpenOk)

    def _send(self, channel: int, value: frame.FrameTypes) -> None:
        self._sock.sendall(frame.marshal(value, channel))

    def _expect(self, kind: type[_Frame]) -> _Frame:
        """The next frame, which must be ``kind`` (handshake and declarations only)."""
        while True:
            if len(self._buffer) >= 8 and len(self._buffer) >= 8 + _HEAD.unpack_from(self._buffer)[2]:  # a whole frame
                used, _, value = frame.unmarshal(bytes(self._buffer))
                if used:
                    del self._buffer[:used]
                    if isinstance(value, (commands.Connection.Close, commands.Channel.Close)):
                        raise BrokerClosed(f"{value.reply_code} {value.reply_text}")
                    if not isinstance(value, kind):
                        raise BrokerClosed(f"expected {kind.__name__}, got {type(value).__name__}")
                    return value
            data = self._sock.recv(65536)
            if not data:
                raise BrokerClosed("the broker closed the socket")
            self._buffer += data

    def bind(self, exchange: str, routing_key: str) -> str:
        """Declare a server-named exclusive queue, bind it; its name."""
        self._send(1, commands.Queue.Declare(queue="", exclusive=True, auto_delete=True))
        name = self._expect(commands.Queue.DeclareOk).queue
        assert name is not None, "Queue.DeclareOk always carries the queue's name"
        self._send(1, commands.Queue.Bind(queue=name, exchange=exchange, routing_key=routing_key))
        self._expect(commands.Queue.BindOk)
        return name

    def consume(self, queue: str) -> None:
        self._send(1, commands.Basic.Consume(queue=queue, no_ack=True))
        self._expect(commands.Basic.ConsumeOk)

    def read(self, arrived: Callable[[Arrival], None], until: Callable[[], bool], poll: float = 0.1) -> None:
        """Hand every delivered message to ``arrived`` until ``until()`` (asked at least every
        ``poll`` s). What came with the handshake's last frame is read first."""
        self._sock.settimeout(poll)
        message = _Message()
        if self._buffer:
            self._parse(time.time_ns(), message, arrived)
        while not until():
            try:
                data = self._sock.recv(262144)
            except socket.timeout:
                continue
            if not data:
                raise BrokerClosed("the broker closed the socket")
            now = time.time_ns()
            self._buffer += data
            self._parse(now, message, arrived)

    def _parse(self, now: int, message: "_Message", arrived: Callable[[Arrival], None]) -> None:
        """Every whole frame in the buffer; a frame cut by the read stays for the next."""
        buffer = self._buffer
        at, length = 0, len(buffer)
        while length - at >= 8:
            kind, _, payload = _HEAD.unpack_from(buffer, at)
            end = at + 7 + payload
            if end >= length:
                break
            if buffer[end] != FRAME_END:
                raise BrokerClosed(f"frame end missing at byte {end}")
            if kind == 3:  # body
                message.body += buffer[at + 7:end]
                if len(message.body) >= message.size:
                    arrived((now, message.key, bytes(message.body)))
                    message.body.clear()
            elif kind == 2:  # content header: class, weight, body size
                (message.size,) = _BODY_SIZE.unpack_from(buffer, at + 11)
                if message.size == 0:
                    arrived((now, message.key, b""))
            elif kind == 1:
                method = _METHOD.unpack_from(buffer, at + 7)
                if method == DELIVER:  # consumer tag, delivery tag, redelivered, exchange, routing key
                    p = at + 11
                    p += 1 + buffer[p] + 8 + 1
                    p += 1 + buffer[p]
                    message.key = buffer[p + 1:p + 1 + buffer[p]].decode()
                elif method in CLOSES:
                    _, _, value = frame.unmarshal(bytes(buffer[at:end + 1]))
                    assert isinstance(value, (commands.Connection.Close, commands.Channel.Close))
                    raise BrokerClosed(f"{CLOSES[method]} closed: {value.reply_code} {value.reply_text}")
            at = end + 1
        del buffer[:at]

    def close(self) -> None:
        try:
            self._send(0, commands.Connection.Close(reply_code=200, reply_text="done", class_id=0, method_id=0))
        except OSError:
            pass
        self._sock.close()
