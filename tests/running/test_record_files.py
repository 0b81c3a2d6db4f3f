"""The recorder's files (engine/running/record.py): rotation by size and by age, the bound on the
total that removes the oldest, and a full queue that drops recorded copies, counted. Read back
with the ``mcap`` library's reader (the summary of each finished file)."""

from __future__ import annotations

import base64
import json
import os
import resource
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from engine.endpoints.base import Inbound, Outbound
from engine.running.record import Recorder, RecordLimits
from tests.support.repo import REPO
from tests.support.waiting import wait_for_sync


def feed(recorder: Recorder, route: str, first: int, count: int) -> None:
    recording = recorder.route(route, "raw_json", {"type": "object"})
    for seq in range(first, first + count):
        body = b'{"seq": %d, "noise": "%s"}' % (seq, base64.b64encode(os.urandom(150)))  # incompressible
        inbound = Inbound(body=body, meta={"topic": f"t/{seq}"})
        recording.received((inbound,))
        recording.sent(Outbound(body, None, None, str(seq), {}, received_ns=inbound.received_ns))


def sequences(path: Path) -> tuple[list[int], dict[str, int]]:
    """The ``seq`` of each canonical message of a finished file, in order (each paired with its
    input: the same receive time, ``publish_time``), and the file's message count per channel."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, f"{path} was not finished"
        received = {message.publish_time: json.loads(message.data)["text"] for _, _, message in reader.iter_messages(topics=["/routes/r/in"])}
        seen = []
        for _, _, message in reader.iter_messages(topics=["/routes/r/canonical"]):
            assert received.get(message.publish_time) == message.data.decode(), "paired with its input by the receive time"
            seen.append(json.loads(message.data)["seq"])
        counts = {summary.channels[key].topic: value for key, value in summary.statistics.channel_message_counts.items()}
    return seen, counts


@pytest.mark.fast
def test_files_rotate_by_size_and_the_oldest_go_past_the_total(tmp_path: Path) -> None:
    limits = RecordLimits(file_bytes=20_000, total_bytes=60_000, flush_s=0.05, chunk_bytes=4_000)
    recorder = Recorder(tmp_path, limits)
    recorder.start()
    try:
        for batch in range(30):  # in steps, as traffic comes: rotation is decided after each flush
            feed(recorder, "r", batch * 40 + 1, 40)

            def caught_up(batch: int = batch) -> bool:
                return recorder.written == (batch + 1) * 80

            wait_for_sync(caught_up, 20, "the writer to catch up", recorder.status)
    finally:
        recorder.stop()
    files = sorted(tmp_path.glob("rabbitros-*.mcap"))
    sizes = [f.stat().st_size for f in files]
    assert recorder.files_removed > 0 and len(files) >= 2, (recorder.status(), sizes)
    assert sum(sizes) <= limits.total_bytes + limits.file_bytes + 2 * limits.chunk_bytes, sizes
    assert all(size < limits.file_bytes + 12 * limits.chunk_bytes for size in sizes), sizes
    kept: list[int] = []
    for path in files:
        seen, counts = sequences(path)
        assert counts["/routes/r/in"] == counts["/routes/r/canonical"] == len(seen), counts
        kept.extend(seen)
    assert kept == list(range(kept[0], 1201)), "the newest are kept, in order, each canonical paired with its input"
    assert recorder.status()["dropped"] == 0


@pytest.mark.fast
def test_files_rotate_by_age(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path, RecordLimits(file_seconds=0.2, flush_s=0.05))
    recorder.start()
    try:
        def three_files() -> bool:
            feed(recorder, "r", 1, 5)
            return len(list(tmp_path.glob("rabbitros-*.mcap"))) >= 3

        wait_for_sync(three_files, 20, "a third file")
    finally:
        recorder.stop()
    for path in sorted(tmp_path.glob("rabbitros-*.mcap")):
        seen, _ = sequences(path)
        assert seen, f"{path} is empty"


@pytest.mark.fast
def test_a_full_queue_drops_recorded_copies_and_counts_them(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path, RecordLimits(queue=10))  # not started: nothing drains it, as a disk that stalled
    feed(recorder, "r", 1, 25)
    status = recorder.status()
    assert status["queued"] == 10 and status["dropped"] == 40 and status["dropped_by_route"] == {"r": 40}, status


FULL_DISK = """
import base64, json, os, signal, sys, time
from pathlib import Path
from engine.endpoints.base import Inbound, Outbound
from engine.running.record import Recorder, RecordLimits
from tests.support.repo import REPO

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past RLIMIT_FSIZE fails with EFBIG, as on a full disk
recorder = Recorder(Path(sys.argv[1]), RecordLimits(flush_s=0.05, chunk_bytes=4000))
recorder.start()
recording = recorder.route("r", "raw_json", {"type": "object"})
fed = 0
deadline = time.monotonic() + 30  # feeds traffic, bounded: the parent asserts write_errors >= 2
while recorder.status()["write_errors"] < 2 and time.monotonic() < deadline:  # two files refused: a retry after the first
    for _ in range(20):
        body = b'{"seq": %d, "noise": "%s"}' % (fed, base64.b64encode(os.urandom(300)))
        inbound = Inbound(body=body, meta={})
        recording.received((inbound,))
        recording.sent(Outbound(body, None, None, str(fed), {}, received_ns=inbound.received_ns))
        fed += 1
    time.sleep(0.02)  # pacing: traffic's pace, not a wait for a condition
recorder.stop()
print(json.dumps({"fed": fed, **recorder.status()}))
"""


@pytest.mark.fast
def test_a_disk_that_refuses_writes_drops_recorded_copies_counted_and_a_new_file_is_tried(tmp_path: Path) -> None:
    """Files capped at 64 KiB (``RLIMIT_FSIZE``: the kernel refuses a write past it, EFBIG, as a
    full disk refuses with ENOSPC), in a child process: the recorder counts every message it
    was handed as written (in a chunk that reached the file) or dropped, never both, never
    neither; it abandons a refused file and opens a new one after ``RETRY_S``; what it counts
    written the ``mcap`` reader reads back from the files."""
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.RLIM_INFINITY))

    result = subprocess.run([sys.executable, "-c", FULL_DISK, str(tmp_path)], cwd=REPO, preexec_fn=limit,
                            capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 0, result.stderr[-3000:]
    status = json.loads(result.stdout.splitlines()[-1])
    assert status["write_errors"] >= 2 and status["dropped"] > 0 and status["written"] > 0, status
    assert status["written"] + status["dropped"] == 2 * status["fed"] and status["queued"] == 0, status
    files = sorted(tmp_path.glob("rabbitros-*.mcap"))
    assert len(files) >= 2, files
    readable = 0
    for path in files:
        with path.open("rb") as stream:
            try:
                for record in StreamReader(stream).records:
                    readable += isinstance(record, Message)
            except (McapError, struct.error):  # the chunk the limit cut short ends the file
                pass
    # written: in a chunk flushed before the failure; of what was logged since the last flush, the
    # chunks that filled up and reached the file before the refused one are readable too, counted dropped
    assert status["written"] <= readable < status["written"] + status["dropped"], (readable, status)
    assert result.stderr.count("recording failed") <= 1, result.stderr[-3000:]  # said once, not per message or per retry
