"""What replay cannot make twice: the keys a mapping takes from the clock or a random id
(engine/language/mapping.py ``unrepeatable_keys``), ours and a protocol's functions alike."""

from __future__ import annotations

import pytest

from engine.language.mapping import unrepeatable_keys

pytestmark = pytest.mark.fast


def test_keys_whose_value_calls_the_clock_or_uuid_nested_as_dotted_paths() -> None:
    mapping = ("{type: 'ack', id: uuid(), stamp: stamp(), at: now(), ref: ref_id, "
               "header: {stamp: to_stamp(t), made: iso8601(now())}, pos: {lat: lat}}")
    assert unrepeatable_keys(mapping) == ["id", "stamp", "at", "header.made"]


def test_a_protocols_reception_time_functions_count_and_exact_conversions_do_not() -> None:
    assert unrepeatable_keys("{stamp: stamp_boot_ms(time_boot_ms), s: stamp_usec(time_usec), e: mav_enum(t, 'MAV_TYPE')}") == ["stamp", "s"]


def test_the_keys_of_the_last_part_of_a_pipe_or_subexpression() -> None:
    assert unrepeatable_keys("[@, f(x)] | {stamp: stamp_boot_ms([0].t), q: [1].q}") == ["stamp"]
    assert unrepeatable_keys("msg.{id: uuid(), n: n}") == ["id"]


@pytest.mark.parametrize("mapping", [None, "", "a.b", "merge(@, {stamp: stamp()})", "{a: a"])
def test_nothing_when_the_keys_are_not_written_out_or_the_mapping_does_not_compile(mapping: str | None) -> None:
    assert unrepeatable_keys(mapping) == []
