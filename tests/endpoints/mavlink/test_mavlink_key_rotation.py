"""MAVLink signing key rotation (issue 21): ``signing: {key_file: new.key, accept: [{key_file:
old.key, until: ...}]}`` accepts frames signed with the old key until its deadline and
refuses them after it; what we send is signed with the new key."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ["MAVLINK20"] = "1"

from engine.endpoints.mavlink.codec import mavlink2  # noqa: E402
from engine.endpoints.mavlink.options import MavlinkAcceptedKey, MavlinkSigning  # noqa: E402
from engine.endpoints.mavlink.settings import load_signing  # noqa: E402
from engine.endpoints.mavlink.signing import SignatureCheck, signing_now  # noqa: E402
from engine.endpoints.mavlink import TRANSPORT  # noqa: E402

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

NEW, OLD, OTHER = bytes(range(32)), bytes(range(32, 64)), bytes(range(64, 96))
DEADLINE = "2026-12-01T00:00:00Z"
DEADLINE_TS = 1_796_083_200.0


def signed(key: bytes, sysid: int, seq: int) -> bytes:
    mav = mavlink2.MAVLink(None, sysid, 1)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = signing_now() + seq
    mav.seq = seq
    return mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav)


def rotation(tmp_path: Path) -> MavlinkSigning:
    (tmp_path / "new.key").write_bytes(NEW)
    (tmp_path / "old.key").write_text(OLD.hex() + "\n")
    return MavlinkSigning(key_file=str(tmp_path / "new.key"),
                          accept=(MavlinkAcceptedKey(key_file=str(tmp_path / "old.key"), until=DEADLINE),))


def test_old_key_accepted_until_its_deadline_and_refused_after(tmp_path: Path):
    config = load_signing(rotation(tmp_path))
    assert config.key == NEW and config.accepted == ((OLD, DEADLINE_TS),)
    now = [DEADLINE_TS - 60]
    check = SignatureCheck(config, signing_now, clock=lambda: now[0])
    assert check(signed(NEW, 1, 1)) is None
    assert check(signed(OLD, 2, 1)) is None  # a vehicle not switched yet
    assert check(signed(OTHER, 3, 1)) == "bad_signature"
    now[0] = DEADLINE_TS  # the deadline: the old key is refused from then on
    assert check(signed(OLD, 2, 2)) == "bad_signature"
    assert check(signed(NEW, 1, 2)) is None


def test_rotation_files_are_watched_and_bad_deadlines_are_check_errors(tmp_path: Path):
    raw = rotation(tmp_path)
    files = TRANSPORT.key_files({"url": "udpin:127.0.0.1:14999", "signing": {
        "key_file": raw.key_file, "accept": [{"key_file": raw.accept[0].key_file, "until": DEADLINE}]}})
    assert sorted(files) == sorted([str(tmp_path / "new.key"), str(tmp_path / "old.key")])
    for until, words in (("2026-12-01T00:00:00", "no time zone"), ("next week", "not an ISO 8601 time")):
        with pytest.raises(ValueError, match=words):
            load_signing(MavlinkSigning(key_file=raw.key_file, accept=(MavlinkAcceptedKey(key_file=raw.accept[0].key_file, until=until),)))
    with pytest.raises(ValueError, match="cannot read key_file"):
        load_signing(MavlinkSigning(key_file=raw.key_file, accept=(MavlinkAcceptedKey(key_file=str(tmp_path / "gone"), until=DEADLINE),)))
