"""JMESPath mappings, compiled once at load, with the functions field work needs.

JMESPath has no arithmetic, clock, ids or string formatting; routes between robots need
all of them (degE7 to degrees, stamps, message ids), so they are registered here as
custom functions. Unit and frame conversions live in :mod:`engine.common.frames`.
"""

from __future__ import annotations

import importlib
import math
import time
import uuid
from functools import lru_cache
from functools import partial as functools_partial
from types import MappingProxyType
from typing import Any, Callable, Mapping, overload

import jmespath
from jmespath import exceptions as jmespath_errors
from jmespath import functions

from engine.common import frames, stamps
from engine.common.placeholders import MappingError, TemplateError, compile_template, template_problem
from engine.language.jmespath_compile import Compiled, compile_parsed
from engine.language.stores import RECALL_FUNCTION, SEQUENCE_FUNCTION, Stores

Mapper = Callable[..., Any]
"""``mapper(data)``, or ``mapper(data, meta)`` where ``meta`` is this message's source metadata
(:attr:`engine.endpoints.base.Inbound.meta`), which ``meta(name)`` reads."""

META_FUNCTION = "meta"
_NO_META: Mapping[str, Any] = MappingProxyType({})


def _frames() -> Any:
    return frames  # imported once at load: an import statement per call cost ~1 us per function


class FieldFunctions(functions.Functions):
    """Custom functions available in every mapping; names are snake_case."""

    @functions.signature({"types": ["number"]}, {"types": ["number"]})
    def _func_mul(self, a: float, b: float) -> float:
        return a * b

    @functions.signature({"types": ["number"]}, {"types": ["number"]})
    def _func_div(self, a: float, b: float) -> float:
        if b == 0:
            raise MappingError("div: division by zero")
        return a / b

    @functions.signature({"types": ["number"]}, {"types": ["number"]})
    def _func_add(self, a: float, b: float) -> float:
        return a + b

    @functions.signature({"types": ["number"]}, {"types": ["number"]})
    def _func_sub(self, a: float, b: float) -> float:
        return a - b

    @functions.signature({"types": ["number"]}, {"types": ["number"], "optional": True})
    def _func_round(self, value: float, digits: int | None = None) -> float:
        return round(value, int(digits)) if digits is not None else round(value)

    @functions.signature({"types": ["number", "string"]})
    def _func_to_int(self, value: Any) -> int:
        return int(float(value))

    @functions.signature({"types": []}, {"types": []})
    def _func_default(self, value: Any, fallback: Any) -> Any:
        return fallback if value is None else value

    @functions.signature()
    def _func_nan(self) -> float:
        """NaN, said explicitly: a typed sink refuses the null a mapping gives for a missing
        path, so a float meant as "unknown" (NavSatFix altitude) must be written as nan()."""
        return math.nan

    @functions.signature()
    def _func_now(self) -> float:
        return time.time()

    @functions.signature()
    def _func_stamp(self) -> dict[str, int]:
        ns = time.time_ns()
        return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}

    # Stamps in their one canonical form {sec, nanosec}, see engine.common.stamps.
    @functions.signature({"types": ["number", "object"]})
    def _func_to_stamp(self, value: Any) -> dict[str, int]:
        return stamps.to_stamp(value)


    @functions.signature({"types": ["number", "object"]})
    def _func_iso8601(self, value: Any) -> str:
        """UNIX seconds or a {sec, nanosec} stamp -> ISO 8601 UTC to the millisecond
        (``2023-11-14T22:13:20.500Z``): the timestamp VDA 5050 messages carry."""
        return stamps.to_iso8601(stamps.to_stamp(value))

    @functions.signature({"types": ["array"]}, {"types": ["array"]})
    def _func_without(self, items: list[Any], removed: list[Any]) -> list[Any]:
        """The elements of ``items`` not in ``removed``, in order: the sensors a vehicle
        enables but does not report healthy (JMESPath's filters cannot read a second array)."""
        return [item for item in items if item not in removed]

    @functions.signature({"types": ["array"]}, {"types": ["array"]}, {"types": ["string"]})
    def _func_upsert(self, items: list[Any], updates: list[Any], key: str) -> list[Any]:
        """``items`` with each record whose field ``key`` an update has replaced by that update
        (in its place), the other updates appended in order: a list of records kept by id, as a
        remembered value updated by several routes (VDA 5050 action states by ``actionId``;
        JMESPath's filters cannot compare with a second array)."""
        by_key = {update.get(key): update for update in updates if isinstance(update, dict)}  # the last update of a key wins
        kept = [by_key.pop(item.get(key), item) if isinstance(item, dict) else item for item in items]
        return kept + list(by_key.values())

    @functions.signature()
    def _func_uuid(self) -> str:
        return uuid.uuid4().hex

    @functions.signature({"types": ["string"]})
    def _func_meta(self, name: str) -> Any:
        """Declared so the function is known; a mapping calling it is compiled with its own
        ``meta`` (:func:`compile_mapping`), which reads the message's metadata."""
        raise MappingError("meta() is evaluated only by a compiled mapping")

    @functions.signature({"types": ["string"]}, {"types": [], "optional": True})
    def _func_recall(self, store: str, key: Any = None) -> Any:
        """Declared so the function is known; a mapping calling it is compiled with the engine's
        stores (:func:`compile_mapping`, engine/language/stores.py)."""
        raise MappingError("recall() is evaluated only by a compiled mapping")

    @functions.signature()
    def _func_sequence(self) -> int:
        """Declared so the function is known; a mapping calling it is compiled with its route's
        counter (:func:`compile_mapping`, engine/language/stores.py)."""
        raise MappingError("sequence() is evaluated only by a compiled mapping")

    @functions.signature({"types": ["array"]}, {"types": ["number"]})
    def _func_skip(self, items: list[Any], count: float) -> list[Any]:
        """The elements after the first ``count`` (``items[count:]`` with a computed count,
        which JMESPath's own slices cannot take): the nodes of an order a vehicle has not
        reached yet, ``skip(nodes, reached)``."""
        return items[max(0, int(count)):]

    @functions.signature({"types": ["string"]}, {"types": ["object"]})
    def _func_format(self, template: str, values: dict[str, Any]) -> str:
        """Fields only (see :func:`parse_template`): never ``str.format``, whose
        ``{agent.__class__.__mro__}`` reads Python attributes when a template comes from a
        message. Parsed templates are cached, so a literal template is parsed once."""
        try:
            return _compiled_template(template)(values)
        except TemplateError as exc:
            raise MappingError(f"format: {exc}") from None

    # Unit and frame conversions (MAVLink integers <-> SI, NED <-> ENU), see engine.common.frames.
    @functions.signature({"types": ["number"]})
    def _func_deg_e7_to_deg(self, value: int) -> float:
        return _frames().deg_e7_to_deg(value)

    @functions.signature({"types": ["number"]})
    def _func_deg_to_deg_e7(self, value: float) -> int:
        return _frames().deg_to_deg_e7(value)

    @functions.signature({"types": ["number"]})
    def _func_mm_to_m(self, value: float) -> float:
        return _frames().mm_to_m(value)

    @functions.signature({"types": ["number"]})
    def _func_m_to_mm(self, value: float) -> int:
        return _frames().m_to_mm(value)

    @functions.signature({"types": ["number"]})
    def _func_cm_to_m(self, value: float) -> float:
        return _frames().cm_to_m(value)

    @functions.signature({"types": ["number"]})
    def _func_m_to_cm(self, value: float) -> int:
        return _frames().m_to_cm(value)

    @functions.signature({"types": ["number"]})
    def _func_cdeg_to_deg(self, value: float) -> float:
        return _frames().cdeg_to_deg(value)

    @functions.signature({"types": ["number"]})
    def _func_deg_to_cdeg(self, value: float) -> int:
        return _frames().deg_to_cdeg(value)

    @functions.signature({"types": ["number"]})
    def _func_rad_to_deg(self, value: float) -> float:
        return math.degrees(value)

    @functions.signature({"types": ["number"]})
    def _func_deg_to_rad(self, value: float) -> float:
        return math.radians(value)

    @functions.signature({"types": ["array", "object"]})
    def _func_ned_to_enu(self, vector: Any) -> Any:
        return _frames().ned_to_enu(vector)

    @functions.signature({"types": ["array", "object"]})
    def _func_enu_to_ned(self, vector: Any) -> Any:
        return _frames().enu_to_ned(vector)

    @functions.signature({"types": ["array", "object"]})
    def _func_aircraft_to_baselink(self, vector: Any) -> Any:
        return _frames().aircraft_to_baselink(vector)

    @functions.signature({"types": ["number"]})
    def _func_heading_cdeg_to_deg(self, value: float) -> float | None:
        return _frames().heading_cdeg_to_deg(value)

    @functions.signature({"types": ["array", "object"]})
    def _func_quat_ned_to_enu(self, quaternion: Any) -> Any:
        return _frames().quat_ned_aircraft_to_enu_baselink(quaternion)

    @functions.signature({"types": ["array", "object"]})
    def _func_quat_enu_to_ned(self, quaternion: Any) -> Any:
        return _frames().quat_enu_baselink_to_ned_aircraft(quaternion)

    @functions.signature({"types": ["number"]}, {"types": ["number"]}, {"types": ["number"]})
    def _func_attitude_to_enu(self, roll: float, pitch: float, yaw: float) -> Any:
        return _frames().attitude_ned_to_enu(roll, pitch, yaw)

    @functions.signature({"types": ["number"]})
    def _func_yaw_to_quaternion(self, yaw: float) -> Any:
        """A heading in the plane (rad, counter-clockwise from x: ENU, a VDA 5050 theta) ->
        the orientation {x, y, z, w} a ROS 2 pose carries."""
        return _frames().quaternion_from_rpy(0.0, 0.0, yaw)

    @functions.signature({"types": ["object", "array"]})
    def _func_quaternion_to_yaw(self, quaternion: Any) -> float:
        """An orientation ({x,y,z,w} or [w,x,y,z]) -> its yaw (rad, [-pi, pi])."""
        return _frames().rpy_from_quaternion(quaternion)["yaw"]

    @functions.signature({"types": ["number"]})
    def _func_wrap_pi(self, angle: float) -> float:
        return _frames().wrap_pi(angle)


_OPTIONS = jmespath.Options(custom_functions=FieldFunctions())
"""The functions every route has; a protocol's own (endpoints.MAPPING_FUNCTIONS) join only in
:func:`_options_for` an expression that calls one, so their libraries load only then."""


@lru_cache(maxsize=1)
def _all_options() -> jmespath.Options:
    """Ours and every protocol's functions (each protocol's module imported now)."""
    from engine import endpoints

    mixins = [importlib.import_module(module).Functions for module in endpoints.MAPPING_FUNCTIONS]
    return jmespath.Options(custom_functions=type("RouteFunctions", (FieldFunctions, *mixins), {})())


def _called(parsed: Any) -> set[str]:
    """The names of the functions an expression calls."""
    return {node["value"] for node in _calls(parsed)}


def _options_for(parsed: Any) -> jmespath.Options:
    from engine import endpoints

    protocol_functions = {name for names in endpoints.MAPPING_FUNCTIONS.values() for name in names}
    return _all_options() if _called(parsed) & protocol_functions else _OPTIONS


@overload
def compile_mapping(expression: str, variables: Mapping[str, Any] | None = None,
                    stores: Stores | None = None, route: str = "") -> Mapper: ...
@overload
def compile_mapping(expression: None, variables: Mapping[str, Any] | None = None,
                    stores: Stores | None = None, route: str = "") -> None: ...
@overload
def compile_mapping(expression: str | None, variables: Mapping[str, Any] | None = None,
                    stores: Stores | None = None, route: str = "") -> Mapper | None: ...
def compile_mapping(expression: str | None, variables: Mapping[str, Any] | None = None,
                    stores: Stores | None = None, route: str = "") -> Mapper | None:
    """Compile a JMESPath expression (to closures, see :mod:`engine.language.jmespath_compile`);
    ``None`` (identity) stays ``None`` so callers can forward original bytes untouched.

    ``meta(name)`` gives the message's source metadata: the mapper is called as
    ``mapper(data, meta)`` with the source's own dict for the message (never copied). The
    call is compiled to a closure reading one slot of this mapper, which ``apply`` points at
    the message's dict before evaluating (one attribute store per message, and none for a
    mapping that does not call ``meta``). A name in ``variables`` (the route's template
    variables, fixed at load) is folded into a constant. Mappings run on the event loop, one
    message at a time, so the slot is never shared by two evaluations in flight.

    ``recall('NAME', key)`` reads store NAME of ``stores`` (the engine's; a fresh, empty set
    when None) and ``sequence()`` counts with the counter of ``route`` there: both resolved
    here, once (engine/language/stores.py)."""
    if expression is None:
        return None
    try:
        parsed = jmespath.compile(expression)
    except jmespath_errors.JMESPathError as exc:
        raise MappingError(_one_line(exc)) from None
    options = _options_for(parsed.parsed)
    called = _called(parsed.parsed)
    overrides: dict[str, Callable[..., Compiled]] = {}
    if RECALL_FUNCTION in called or SEQUENCE_FUNCTION in called:
        stores = stores if stores is not None else Stores()
        overrides[RECALL_FUNCTION] = functools_partial(_compile_recall, stores)
        overrides[SEQUENCE_FUNCTION] = functools_partial(_compile_sequence, stores, route)
    slot = _MetaSlot()
    if META_FUNCTION in called:
        constants = dict(variables or {})

        def compile_meta(node: dict[str, Any], compile_node: Callable[[Any], Compiled]) -> Compiled:
            name = meta_name(node)
            if name is None:
                raise MappingError("meta() takes one name in quotes, as meta('routing_key')")
            if name in constants:
                constant = constants[name]
                return lambda value: constant

            def meta(value: Any) -> Any:
                return slot.meta.get(name)

            return meta

        overrides[META_FUNCTION] = compile_meta
    evaluate = compile_parsed(parsed, options, overrides or None)
    if META_FUNCTION not in called:

        def apply(data: Any, meta: Mapping[str, Any] = _NO_META) -> Any:
            try:
                return evaluate(data)
            except jmespath_errors.JMESPathError as exc:
                raise MappingError(_one_line(exc)) from None
            except (TypeError, ValueError, ArithmeticError) as exc:
                raise MappingError(str(exc)) from None

        return apply

    def apply_with_meta(data: Any, meta: Mapping[str, Any] = _NO_META) -> Any:
        slot.meta = meta
        try:
            return evaluate(data)
        except jmespath_errors.JMESPathError as exc:
            raise MappingError(_one_line(exc)) from None
        except (TypeError, ValueError, ArithmeticError) as exc:
            raise MappingError(str(exc)) from None

    return apply_with_meta


def _compile_recall(stores: Stores, node: dict[str, Any], compile_node: Callable[[Any], Compiled]) -> Compiled:
    """``recall('NAME')`` or ``recall('NAME', key)``: the store is looked up now, the key
    expression compiled as any other; per message one or two dict lookups."""
    children = node.get("children", ())
    name = literal_name(node)
    if name is None or len(children) > 2:
        raise MappingError("recall() takes a store name in quotes and a key, as recall('position', serialNumber)")
    store = stores.store(name)
    if len(children) == 1:
        return lambda value: store.get(None)
    key = compile_node(children[1])
    return lambda value: store.get(key(value))


def _compile_sequence(stores: Stores, route: str, node: dict[str, Any], compile_node: Callable[[Any], Compiled]) -> Compiled:
    if node.get("children"):
        raise MappingError("sequence() takes no argument")
    counter = stores.sequence(route) if route else Stores().sequence("")
    return lambda value: next(counter)


class _MetaSlot:
    """Where a compiled ``meta(name)`` finds the metadata of the message being mapped."""

    __slots__ = ("meta",)

    def __init__(self) -> None:
        self.meta: Mapping[str, Any] = _NO_META


def meta_name(node: dict[str, Any]) -> str | None:
    """The name a ``meta(...)`` call node asks for, or None when it is not one literal string."""
    children = node.get("children", ())
    return literal_name(node) if len(children) == 1 else None


def literal_name(node: dict[str, Any]) -> str | None:
    """The literal string a call node (``meta``, ``recall``) gives first, or None."""
    children = node.get("children", ())
    if children and children[0].get("type") == "literal" and isinstance(children[0].get("value"), str):
        return children[0]["value"]
    return None


def recall_names(expression: str | None) -> list[str | None]:
    """The store names ``expression`` passes to ``recall()``, in order (None for a call that
    does not give one literal name); [] for an expression that does not compile."""
    return [literal_name(node) for node in _calls(parsed(expression), RECALL_FUNCTION)]


def meta_names(expression: str | None) -> list[str | None]:
    """The names ``expression`` passes to ``meta()``, in order (None for a call that does not
    give one literal name); [] for an expression that does not compile."""
    return [meta_name(node) for node in _calls(parsed(expression), META_FUNCTION)]


def parsed(expression: str | None) -> dict[str, Any]:
    """The parse tree of ``expression``; an empty tree when there is none or it does not compile
    (the compile error is reported where the mapping is compiled, not by the checks reading it)."""
    if not expression:
        return {}
    try:
        return jmespath.compile(expression).parsed
    except jmespath_errors.JMESPathError:
        return {}


def _calls(node: Any, function: str | None = None) -> list[dict[str, Any]]:
    """The function-call nodes of a parsed expression (of ``function`` only, if given)."""
    found: list[dict[str, Any]] = []
    stack = [node]
    while stack:
        current = stack.pop()
        if not isinstance(current, dict):
            continue
        if current.get("type") == "function_expression" and function in (None, current.get("value")):
            found.append(current)
        stack.extend(reversed(current.get("children", ())))
    return found


UNREPEATABLE = ("now", "stamp", "uuid")
"""Functions whose value differs at every evaluation: the clock and a random id (a protocol's
``Functions`` class names its own in ``UNREPEATABLE``)."""


def _unrepeatable_functions() -> set[str]:
    from engine import endpoints

    return {*UNREPEATABLE, *(name for module in endpoints.MAPPING_FUNCTIONS
                             for name in getattr(importlib.import_module(module).Functions, "UNREPEATABLE", ()))}


def unrepeatable_keys(expression: str | None) -> list[str]:
    """The keys (``a.b`` when nested) of a mapping's multi-select hash whose value calls one of
    :data:`UNREPEATABLE` (``{stamp: stamp(), header: {id: uuid()}}`` -> ``stamp``,
    ``header.id``): no replay can make them again, so ``replay`` leaves them out of its
    comparison and says which (engine/ops/replay.py)."""
    found: list[str] = []
    unrepeatable = _unrepeatable_functions()

    def visit(node: dict[str, Any], prefix: str) -> None:
        for pair in node.get("children", ()):
            key, value = prefix + pair["value"], pair["children"][0]
            if value.get("type") == "multi_select_dict":
                visit(value, key + ".")
            elif _called(value) & unrepeatable:
                found.append(key)

    tree = parsed(expression)
    while tree.get("type") in ("pipe", "subexpression"):  # ``[@, f(x)] | {...}``: the result is the last part's
        tree = tree["children"][-1]
    if tree.get("type") == "multi_select_dict":
        visit(tree, "")
    return found


def known_functions() -> list[str]:
    """Every function a mapping may call: JMESPath's own, ours and the protocols'."""
    return sorted(_all_options().custom_functions.FUNCTION_TABLE)


def unknown_functions(expression: str) -> list[str]:
    """Function names used by ``expression`` that neither JMESPath nor we define.

    JMESPath resolves function names only when evaluating; a typo in a route must
    fail ``check`` instead of the first message.
    """
    called = _called(jmespath.compile(expression).parsed)
    unknown = called - set(_OPTIONS.custom_functions.FUNCTION_TABLE)
    if unknown:  # a protocol's function, or a typo
        unknown -= set(_all_options().custom_functions.FUNCTION_TABLE)
    return sorted(unknown)


def top_level_keys(expression: str | None) -> list[str] | None:
    """Keys of a ``{a: x, b: y}`` mapping, for static checks of typed sinks; None otherwise."""
    if expression is None:
        return None
    node = jmespath.compile(expression).parsed
    if node.get("type") != "multi_select_dict":
        return None
    return [child["value"] for child in node["children"]]


@lru_cache(maxsize=512)
def _compiled_template(template: str) -> Callable[[Any], str]:
    return compile_template(template)


def literal_format_problems(expression: str) -> list[str]:
    """Problems of the literal templates given to ``format()`` in ``expression``, so a bad
    one fails ``check`` rather than the first message."""
    problems: list[str] = []

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            children = node.get("children", ())
            if node.get("type") == "function_expression" and node.get("value") == "format" and children:
                first = children[0]
                if isinstance(first, dict) and first.get("type") == "literal" and isinstance(first.get("value"), str):
                    problem = template_problem(first["value"])
                    if problem:
                        problems.append(f"format(): {problem}")
            for child in children:
                walk(child)

    walk(jmespath.compile(expression).parsed)
    return problems


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())
