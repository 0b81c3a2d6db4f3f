"""ROS 2 message <-> plain dict, for any installed message type, by rosbridge's JSON conventions.

Types are resolved by name at run time (``pkg/msg/Type`` or ``pkg/Type``) from the installed
Python packages, so a route can name any message without a build step. The rules follow
rosbridge (see ``shared/research/ros_bridges.md`` section 3) so its clients interoperate:

* nested messages are objects; ``builtin_interfaces/Time`` and ``Duration`` are
  ``{"sec", "nanosec"}`` (``secs``/``nsecs`` are accepted on input), and a Time given as
  the string ``"now"`` is the wall clock now (rosbridge's ``_to_time_inst``);
* exactly what rosbridge's ``message_conversion.py`` base64-encodes is base64 on output:
  ``uint8`` arrays (``uint8[N]``) and unbounded sequences (``uint8[]``), where a ``.msg``
  ``char`` is a ``uint8`` too. A bounded ``uint8`` sequence (``uint8[<=N]``) is a list of
  ints, and so is any ``byte`` (``octet``) array or sequence: rosbridge emits those element
  by element (its ``_from_list_inst``), and a single ``byte`` as an int. Input takes base64
  or a list of ints for all of them;
* non-finite floats become ``null`` on output, scalars and arrays alike (rosbridge's arrays
  emit bare ``NaN``, which is not JSON). ``null`` reads back as NaN so that a message survives
  a ROS -> JSON -> ROS round trip, which rosbridge rejects; but not from a sink mapping
  (``from_dict(..., null_as_nan=False)``): there a null is a value the mapping did not find,
  and :class:`NullValue` refuses it wherever it is, rather than publish a NaN or a default;
* input is strict: unknown fields and wrong value types raise :class:`MessageError` naming
  the field path (``poses[2].position.w``); missing fields keep their defaults; a
  ``std_msgs/Header`` whose stamp is absent or zero is stamped with the wall clock now.

Generated message classes no longer check values (``ROS_PYTHON_CHECK_FIELDS`` is off by
default in Jazzy), so the checks here are what keeps a bad value from being truncated in C.
Each type's converters are built once from its ``SLOT_TYPES`` and cached; the per-message
path only walks precomputed ``(name, slot, converter)`` tuples and writes the slots directly.
"""

from __future__ import annotations

import array
import base64
import binascii
import importlib
import math
import re
import time
from functools import lru_cache
from collections.abc import Mapping
from typing import Any, Callable, TypeAlias

import numpy
from rosidl_parser import definition as idl

__all__ = ["MessageError", "NullValue", "null_path", "resolve_type", "type_name", "field_names", "nested_type", "to_dict", "from_dict"]


class MessageError(ValueError):
    """A type name or a value does not fit a ROS message; ``path`` locates the field."""

    def __init__(self, reason: str, path: list[str | int] | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.path: list[str | int] = path if path is not None else []

    @property
    def field(self) -> str:
        out = ""
        for part in self.path:
            out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
        return out

    def __str__(self) -> str:
        return f"field {self.field}: {self.reason}" if self.path else self.reason


class NullValue(MessageError):
    """A null where the message needs a value, from data that must not default it (a sink
    mapping's output: JMESPath gives null for a path the message lacks)."""

    def __init__(self, path: list[str | int] | None = None) -> None:
        super().__init__("null (the sink mapping gave no value: JMESPath gives null for a path the message "
                         "lacks); leave the field out to keep its default, or give nan() for a float meant as NaN", path)


RosClass: TypeAlias = Any
"""A class rosidl generated: a message, or a service or action (with its ``Request``, ``Goal``
...). Typed Any: its fields are read at run time (``get_fields_and_field_types``,
``SLOT_TYPES``), and mypy 2.x takes no ``type[...]`` as Hashable for the caches below."""

_TYPE_NAME = re.compile(r"^([a-z][a-z0-9_]*)/(?:msg/)?([A-Z][A-Za-z0-9]*)$")


@lru_cache(maxsize=None)
def resolve_type(name: str) -> RosClass:
    """The message class for ``pkg/msg/Type`` or ``pkg/Type``; MessageError if not installed."""
    match = _TYPE_NAME.match(name.strip()) if isinstance(name, str) else None
    if match is None:
        raise MessageError(f"type name {name!r} is not of the form pkg/msg/Type")
    pkg, cls_name = match.groups()
    full = f"{pkg}/msg/{cls_name}"
    try:
        module = importlib.import_module(f"{pkg}.msg")
    except ImportError:
        raise MessageError(f"type '{full}' is not installed") from None
    cls = getattr(module, cls_name, None)
    if not isinstance(cls, type) or not hasattr(cls, "SLOT_TYPES"):
        raise MessageError(f"type '{full}' is not installed")
    return cls


def type_name(cls: RosClass) -> str:
    """``pkg/msg/Type`` of a message class (the form ROS tools print); a service's or an
    action's parts are ``pkg/srv/Type_Response``, ``pkg/action/Type_Feedback``."""
    package, kind = (cls.__module__.split(".") + ["msg"])[:2]
    return f"{package}/{kind}/{cls.__name__}"


def field_names(cls: RosClass) -> tuple[str, ...]:
    return tuple(cls.get_fields_and_field_types())


def nested_type(cls: RosClass, field: str) -> RosClass | None:
    """The message class of ``field`` when it holds one nested message, else None."""
    for name, slot_type in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES):
        if name == field and isinstance(slot_type, idl.NamespacedType):
            return _class_of(slot_type)
    return None


def null_path(data: Any) -> list[str | int] | None:
    """Where the first null in ``data`` is (``["pose", "pose", "position", "x"]``, ``[]`` for
    ``data`` itself), or None: what ``from_dict(..., null_as_nan=False)`` refuses, found
    without building the message."""
    if data is None:
        return []
    if isinstance(data, Mapping):
        items: Any = data.items()
    elif isinstance(data, (list, tuple)):
        items = enumerate(data)
    else:
        return None
    for key, value in items:
        if value is None:
            return [key]
        if isinstance(value, (Mapping, list, tuple)):
            inner = null_path(value)
            if inner is not None:
                return [key, *inner]
    return None


def to_dict(msg: Any) -> dict[str, Any]:
    cls: RosClass = type(msg)
    return _to_dict_fn(cls)(msg)


def from_dict(cls: RosClass, data: Mapping[str, Any], null_as_nan: bool = True) -> Any:
    """The message of ``data``. ``null_as_nan=False`` refuses every null (:class:`NullValue`),
    for data a sink mapping made; otherwise a null float reads as NaN (see the module)."""
    return _from_dict_fn(cls, not null_as_nan)(data)


def _class_of(t: idl.NamespacedType) -> RosClass:
    return resolve_type(f"{t.namespaces[0]}/{t.name}")


def _slots(cls: RosClass) -> list[tuple[str, str, Any]]:
    return [(name, f"_{name}", t) for name, t in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES)]


_INT_RANGE = {
    "int8": (-(2**7), 2**7 - 1), "uint8": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1), "uint64": (0, 2**64 - 1),
    "short": (-(2**15), 2**15 - 1), "unsigned short": (0, 2**16 - 1),
    "long": (-(2**31), 2**31 - 1), "unsigned long": (0, 2**32 - 1),
    "long long": (-(2**63), 2**63 - 1), "unsigned long long": (0, 2**64 - 1),
}
_FLOATS = ("float", "double", "long double")
# What rosidl_generator_py stores numeric arrays in: array.array for sequences, numpy for arrays.
_TYPECODE = {"float": "f", "double": "d", "int8": "b", "uint8": "B", "int16": "h", "uint16": "H",
             "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q"}
_FLOAT32_MAX = 3.4028234663852886e38
_isfinite = math.isfinite
_NAN = float("nan")


def _is_bytes(t: idl.AbstractNestedType) -> bool:
    return isinstance(t.value_type, idl.BasicType) and t.value_type.typename in ("uint8", "octet")


def _is_base64(t: idl.AbstractNestedType) -> bool:
    """What rosbridge base64-encodes: ``uint8[N]`` and ``sequence<uint8>``, not a bounded
    ``sequence<uint8, N>`` nor ``octet`` (its ``ros_binary_types`` after the bracket rewrite)."""
    return (isinstance(t.value_type, idl.BasicType) and t.value_type.typename == "uint8"
            and not isinstance(t, idl.BoundedSequence))


# ---------------------------------------------------------------- message -> dict

@lru_cache(maxsize=None)
def _to_dict_fn(cls: RosClass) -> Callable[[Any], dict[str, Any]]:
    fields = tuple((name, slot, _out(t)) for name, slot, t in _slots(cls))

    def convert(msg: Any) -> dict[str, Any]:
        out = {}
        for name, slot, conv in fields:
            value = getattr(msg, slot)
            out[name] = value if conv is None else conv(value)
        return out

    return convert


def _finite(x: float) -> float | None:
    return x if _isfinite(x) else None


def _float_list(values: Any) -> list[float | None]:
    out = values.tolist()
    if all(map(_isfinite, out)):
        return out
    return [x if _isfinite(x) else None for x in out]


def _b64(values: Any) -> str:
    raw = b"".join(values) if isinstance(values, list) else values
    return base64.b64encode(raw).decode("ascii")


def _out(t: Any) -> Callable[[Any], Any] | None:
    """How one field's stored value becomes JSON-ready; None when it already is."""
    if isinstance(t, idl.BasicType):
        if t.typename in _FLOATS:
            return _finite
        return ord if t.typename == "octet" else None
    if isinstance(t, idl.NamespacedType):
        return _to_dict_fn(_class_of(t))
    if isinstance(t, idl.AbstractNestedType):
        if _is_base64(t):
            return _b64
        inner = t.value_type
        if isinstance(inner, idl.BasicType) and inner.typename in _TYPECODE:
            return _float_list if inner.typename in _FLOATS else _tolist
        if isinstance(inner, idl.NamespacedType):
            sub = _to_dict_fn(_class_of(inner))
            return lambda values: [sub(m) for m in values]
        item = _out(inner)
        return list if item is None else (lambda values: [item(v) for v in values])
    return None


def _tolist(values: Any) -> list[Any]:
    return values.tolist()


# ---------------------------------------------------------------- dict -> message

def _describe(value: Any) -> str:
    if value is None:
        return "null"
    text = repr(value)
    return f"{type(value).__name__} {text}" if len(text) <= 40 else type(value).__name__


def _mismatch(expected: str, value: Any) -> MessageError:
    return MessageError(f"expected {expected}, got {_describe(value)}")


def _now_stamp(stamp_cls: RosClass) -> Any:
    ns = time.time_ns()
    return stamp_cls(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@lru_cache(maxsize=None)
def _from_dict_fn(cls: RosClass, strict: bool = False) -> Callable[[Any], Any]:
    """Build messages with ``__new__`` and fill every slot once: the generated ``__init__``
    would first build default sub-messages that the input then replaces. ``strict``: every
    null is a :class:`NullValue`."""
    tname = type_name(cls)
    slots = _slots(cls)
    fields = {name: (slot, _in(t, strict)) for name, slot, t in slots}
    prototype = cls()
    defaults = tuple((name, slot, _default_factory(t, getattr(prototype, slot))) for name, slot, t in slots)
    field_slots = {slot for _, slot, _ in slots}
    extra = tuple((slot, getattr(prototype, slot)) for slot in cls.__slots__ if slot not in field_slots)
    aliases = _TIME_ALIASES if tname in _TIME_TYPES else None
    stamp_cls = nested_type(cls, "stamp") if tname == "std_msgs/msg/Header" else None
    n_fields = len(fields)
    new = cls.__new__
    is_time = tname == "builtin_interfaces/msg/Time"

    def convert(data: Any) -> Any:
        if type(data) is not dict and not isinstance(data, Mapping):
            if is_time and data == "now":
                return _now_stamp(cls)
            if strict and data is None:
                raise NullValue()
            raise _mismatch(f"an object ({tname})", data)
        if aliases is not None and not aliases.keys().isdisjoint(data):
            data = {aliases.get(k, k): v for k, v in data.items()}
        msg = new(cls)
        for key, value in data.items():
            try:
                slot, conv = fields[key]
            except KeyError:
                raise MessageError(f"unknown field of {tname}", [key]) from None
            if strict and value is None:
                raise NullValue([key])
            try:
                setattr(msg, slot, conv(value))
            except MessageError as exc:
                exc.path.insert(0, key)
                raise
        if len(data) != n_fields:
            for name, slot, make in defaults:
                if name not in data:
                    setattr(msg, slot, make())
        for slot, value in extra:
            setattr(msg, slot, value)
        if stamp_cls is not None and not (msg._stamp._sec or msg._stamp._nanosec):
            msg._stamp = _now_stamp(stamp_cls)
        return msg

    return convert


_TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")
_TIME_ALIASES = {"secs": "sec", "nsecs": "nanosec"}
_EMPTY: Mapping[str, Any] = {}


def _default_factory(t: Any, value: Any) -> Callable[[], Any]:
    """A fresh default for a missing field; nested messages go through the converter so that
    their headers get stamped too."""
    if isinstance(t, idl.NamespacedType):
        build = _from_dict_fn(_class_of(t))
        return lambda: build(_EMPTY)
    if isinstance(t, idl.Array) and isinstance(t.value_type, idl.NamespacedType):
        build, size = _from_dict_fn(_class_of(t.value_type)), t.size
        return lambda: [build(_EMPTY) for _ in range(size)]
    if isinstance(value, numpy.ndarray):
        return value.copy
    if isinstance(value, (list, array.array)):
        return lambda: value[:]
    return lambda: value


def _in(t: Any, strict: bool = False) -> Callable[[Any], Any]:
    """How one JSON value becomes what the message class stores for a field of type ``t``."""
    if isinstance(t, idl.BasicType):
        return _basic_in(t.typename, strict)
    if isinstance(t, idl.AbstractGenericString):
        limit = t.maximum_size if t.has_maximum_size() else None
        return _string_in(limit)
    if isinstance(t, idl.NamespacedType):
        return _from_dict_fn(_class_of(t), strict)
    if isinstance(t, idl.AbstractNestedType):
        return _nested_in(t, strict)
    raise MessageError(f"unsupported field type {t!r}")


def _basic_in(typename: str, strict: bool = False) -> Callable[[Any], Any]:
    if typename == "boolean":
        def boolean(v: Any) -> bool:
            if type(v) is bool:
                return v
            raise _mismatch("bool", v)
        return boolean
    if typename in _FLOATS:
        limit = _FLOAT32_MAX if typename == "float" else None

        def real(v: Any) -> float:
            kind = type(v)
            if kind is float:
                if limit is not None and _isfinite(v) and abs(v) > limit:
                    raise MessageError(f"{v!r} is out of range for float32")
                return v
            if kind is int:
                try:
                    return real(float(v))
                except OverflowError:
                    raise MessageError(f"{v} is out of range for {typename}") from None
            if v is None:
                if strict:
                    raise NullValue()
                return _NAN
            raise _mismatch(typename if typename != "float" else "float32", v)
        return real
    if typename in _INT_RANGE:
        lo, hi = _INT_RANGE[typename]

        def integer(v: Any) -> int:
            if type(v) is int and lo <= v <= hi:
                return v
            if type(v) is int:
                raise MessageError(f"{v} is out of range for {typename}")
            raise _mismatch(typename, v)
        return integer
    if typename == "octet":
        def octet(v: Any) -> bytes:
            if type(v) is int and 0 <= v <= 255:
                return bytes((v,))
            raise _mismatch("byte (int 0..255)", v)
        return octet
    if typename in ("char", "wchar"):
        def char(v: Any) -> str:
            if type(v) is str and len(v) == 1:
                return v
            raise _mismatch("a one-character string", v)
        return char
    raise MessageError(f"unsupported basic type {typename!r}")


def _string_in(limit: int | None) -> Callable[[Any], str]:
    def string(v: Any) -> str:
        if type(v) is not str:
            raise _mismatch("string", v)
        if limit is not None and len(v) > limit:
            raise MessageError(f"string longer than {limit}")
        return v
    return string


def _check_length(t: idl.AbstractNestedType, n: int) -> None:
    if isinstance(t, idl.Array) and n != t.size:
        raise MessageError(f"expected {t.size} items, got {n}")
    if isinstance(t, idl.BoundedSequence) and n > t.maximum_size:
        raise MessageError(f"expected at most {t.maximum_size} items, got {n}")


def _nested_in(t: idl.AbstractNestedType, strict: bool = False) -> Callable[[Any], Any]:
    inner = t.value_type
    fixed = isinstance(t, idl.Array)
    if _is_bytes(t):
        return _bytes_in(t, octets=inner.typename == "octet", fixed=fixed, strict=strict)
    item = _in(inner, strict)
    if isinstance(inner, idl.BasicType) and inner.typename in _TYPECODE:
        return _numbers_in(t, inner.typename, item, fixed, strict)

    def items(v: Any) -> list[Any]:
        if not isinstance(v, (list, tuple)):
            raise _mismatch("an array", v)
        _check_length(t, len(v))
        return _each(v, item, strict)
    return items


def _each(values: Any, item: Callable[[Any], Any], strict: bool) -> list[Any]:
    """``item`` of every element; a failure names the element's index in its path."""
    out = []
    for i, x in enumerate(values):
        if strict and x is None:
            raise NullValue([i])
        try:
            out.append(item(x))
        except MessageError as exc:
            exc.path.insert(0, i)
            raise
    return out


def _numbers_in(t: idl.AbstractNestedType, typename: str, item: Callable[[Any], Any],
                fixed: bool, strict: bool = False) -> Callable[[Any], Any]:
    code = _TYPECODE[typename]
    dtype = numpy.dtype(code)
    is_float = typename in _FLOATS
    fast_types = ({float}, {int}, {float, int}) if is_float else ({int},)

    def numbers(v: Any) -> Any:
        if not isinstance(v, (list, tuple)):
            raise _mismatch("an array", v)
        _check_length(t, len(v))
        kinds = set(map(type, v))
        values = None
        if not kinds or kinds in fast_types:
            try:
                values = array.array(code, v)
            except OverflowError:
                pass
            else:
                if code == "f" and not all(map(_isfinite, values)):
                    values = None  # array("f") turns an out-of-range float into inf silently
        if values is None:
            values = array.array(code, _each(v, item, strict))
        return numpy.frombuffer(values, dtype=dtype).copy() if fixed else values
    return numbers


def _bytes_in(t: idl.AbstractNestedType, octets: bool, fixed: bool, strict: bool = False) -> Callable[[Any], Any]:
    def raw_bytes(v: Any) -> Any:
        if strict and isinstance(v, (list, tuple)) and None in v:
            raise NullValue([v.index(None)])
        if isinstance(v, str):
            try:
                raw = base64.b64decode(v, validate=True)
            except (binascii.Error, ValueError):
                raise MessageError("expected a base64 string or a list of ints 0..255") from None
        elif isinstance(v, (list, tuple)):
            try:
                raw = bytes(v)
            except (TypeError, ValueError):
                raise MessageError("expected a base64 string or a list of ints 0..255") from None
            if bool in set(map(type, v)):
                raise MessageError("expected a list of ints 0..255, got a bool")
        else:
            raise _mismatch("a base64 string or a list of ints", v)
        _check_length(t, len(raw))
        if octets:
            return [raw[i:i + 1] for i in range(len(raw))]
        return numpy.frombuffer(raw, dtype=numpy.uint8).copy() if fixed else array.array("B", raw)
    return raw_bytes
