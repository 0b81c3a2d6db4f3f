"""The recorder's files (engine/running/record.py): rotation by size and by age, the bound on the
total that removes the oldest, and a full queue that drops recorded copies, counted. Read back
with the ``mcap`` library's reader (the summary of each finished file)."""

from __future__ import annotations

import base64
import json
import os
from pathlib import Path

import pytest
from mcap.reader import make_reader

from engine.endpoints.base import Inbound, Outbound
from engine.running.record import Recorder, RecordLimits
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
            wait_for_sync(lambda batch=batch: recorder.written == (batch + 1) * 80, 20, "the writer to catch up",
                          recorder.status)
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
