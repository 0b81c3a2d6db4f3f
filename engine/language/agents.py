"""The agents table: the fleet's members by name, so routes say ``uav2`` instead of ``2``.

A route file's top-level ``agents:`` maps names to objects of values (names unique across the
directory, as connections are)::

    agents:
      uav1: {connection: radio, system_id: 1}
      uav2: {connection: radio, system_id: 2}
      robot1: {namespace: /robot1}

The core gives the values no meaning but one: ``connection`` is the connection the agent is
reached over. What the other keys mean belongs to the protocol: a transport names the options
that take an agent's name and the entry key giving their value (``Transport.agent_options``:
MAVLink's ``system_id`` and ``target_system`` take the agent's ``system_id``), and whether an
endpoint looks agents up per message (``Transport.looks_up_agents``: a sink whose
``target_system: "{vehicle}"`` may read ``uav2``). Three uses:

* ``for_each: agents`` expands a route once per agent that has every variable the route uses
  (``{agent}`` is the name, the other variables the entry's keys): the fleet idiom;
* an agent's name where an option takes one is replaced at load by the entry's value, and the
  endpoint's connection defaults to (and must be) the agent's; an unknown name is a ``check``
  error with a did-you-mean;
* an endpoint that looks agents up per message gets the entries on its connection (its
  ``agents`` option, set by the loader): a sink resolves a ``{field}`` holding a name, and a
  message naming no agent is dead-lettered naming the field, never sent to a guessed vehicle; a
  source gives ``meta('agent')``, the name of the agent it heard.

The route's fingerprint covers the entries it uses (its for_each item, the names its options
give, the table of its connection where it looks agents up), so editing one agent's entry
reloads only the routes that use it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeGuard

from engine.common.suggest import did_you_mean

AGENTS = "agents"
"""The top-level key of the table, and the ``for_each`` value that expands over it."""
AGENT = "agent"
"""The template variable (and metadata name) holding an agent's name."""
CONNECTION = "connection"
"""The one entry key the core reads: the connection the agent is reached over."""

Table = Mapping[str, Mapping[str, Any]]


def items(table: Table) -> list[dict[str, Any]]:
    """The table as ``for_each`` items: ``{agent: NAME, **entry}`` per agent, in order."""
    return [{AGENT: name, **entry} for name, entry in table.items()]


def on_connection(table: Table, connection: str) -> dict[str, dict[str, Any]]:
    """The agents reached over ``connection``: those naming it, and those naming none."""
    return {name: dict(entry) for name, entry in table.items() if entry.get(CONNECTION, connection) == connection}


def resolve(table: Table, name: str, key: str) -> tuple[Any, str | None, str | None]:
    """``(value, agent's connection, problem)`` of ``name``'s entry ``key`` (an option that
    takes an agent's name); the problem says what is wrong, with a did-you-mean."""
    entry = table.get(name)
    if entry is None:
        known = f" (agents: {', '.join(table)})" if table else " (no agents table: a top-level agents: mapping names them)"
        return None, None, f"unknown agent {name!r}{did_you_mean(name, table) or known}"
    if key not in entry:
        return None, None, f"agent {name!r} has no {key!r} (its keys: {', '.join(entry) or 'none'})"
    return entry[key], entry.get(CONNECTION), None


def is_name(value: Any) -> TypeGuard[str]:
    """Whether an option's value is an agent's name: text that is neither a number nor a
    ``{field}`` read from the message."""
    return isinstance(value, str) and not value.startswith("{") and not value.lstrip("-").isdigit()
