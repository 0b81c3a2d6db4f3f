"""JMESPath expressions compiled to Python closures, with exactly the ``jmespath`` results.

``jmespath.search`` walks the parsed tree for every message: a dispatch per node, a new
``TreeInterpreter`` and its method cache per call. A route evaluates the same expression
millions of times, so the tree is turned once into nested closures, one per node, each
doing what ``jmespath.visitor.TreeInterpreter.visit_<node>`` does (same truthiness, same
comparisons, same ``None`` for a missing field or a wrong type, same function table with
its argument type checks, same exceptions). Field paths (``a.b.c``) become one loop.

Every node type of jmespath 1.x is compiled; a node type this module does not know (a
future jmespath) makes the whole expression fall back to jmespath's own interpreter, so a
result is never a guess. tests/language/test_jmespath_compile.py compares both on generated
expressions and documents and on every mapping the project ships.
"""

from __future__ import annotations

import operator
from typing import Any, Callable

from jmespath import functions as jmespath_functions
from jmespath.parser import ParsedResult
from jmespath.visitor import Options, TreeInterpreter, _equals, _is_actual_number, _is_comparable
from jmespath.visitor import _Expression as _InterpretedExpression

Compiled = Callable[[Any], Any]
Override = Callable[[dict[str, Any], Callable[[Any], Compiled]], Compiled]
"""Compiles one ``function_expression`` node itself (a function that needs more than its
arguments, such as ``meta(name)``, which reads the message's source metadata, or ``recall``,
which reads a store); it is given the node and the compiler of its argument nodes."""


class Unsupported(Exception):
    """A node this compiler does not know; the caller falls back to the interpreter."""


def compile_parsed(parsed: ParsedResult, options: Options | None = None,
                   overrides: dict[str, Override] | None = None) -> Compiled:
    """A callable equal to ``lambda data: parsed.search(data, options=options)``.

    ``overrides`` compile calls of the functions they name (by name) instead of the function
    table; an expression using one never falls back to the interpreter (it raises Unsupported)."""
    try:
        return _Compiler(options or Options(), overrides).node(parsed.parsed)
    except Unsupported:
        if overrides:
            raise
        return lambda data: parsed.search(data, options=options)


def is_compiled(parsed: ParsedResult) -> bool:
    """Whether every node of ``parsed`` compiles (for tests and ``check`` reports)."""
    try:
        _Compiler(Options()).node(parsed.parsed)
    except Unsupported:
        return False
    return True


def _is_false(value: Any) -> bool:
    # As TreeInterpreter._is_false: JMESPath's falsy values, by equality, not Python truth.
    return value == "" or value == [] or value == {} or value is None or value is False


def _identity(value: Any) -> Any:
    return value


def _project(right: Compiled, elements: Any) -> list[Any]:
    """A projection's right side over each element; None results are left out."""
    collected = []
    for element in elements:
        current = right(element)
        if current is not None:
            collected.append(current)
    return collected


class _Expression(_InterpretedExpression):
    """An expression reference (``&field``) handed to functions such as ``sort_by``.

    jmespath's functions type-check it by class name (``_Expression``) and evaluate it
    with ``expref.visit(expref.expression, value)``; this one runs the compiled closure."""

    def __init__(self, expression: dict[str, Any], compiled: Compiled, options: Options) -> None:
        super().__init__(expression, TreeInterpreter(options))
        self._compiled = compiled

    def visit(self, node: Any, *args: Any, **kwargs: Any) -> Any:
        if node is self.expression:
            return self._compiled(*args, **kwargs)
        return self.interpreter.visit(node, *args, **kwargs)  # not used by jmespath's own functions


class _Compiler:
    def __init__(self, options: Options, overrides: dict[str, Override] | None = None) -> None:
        self.options = options
        self.overrides = overrides or {}
        self.functions = options.custom_functions if options.custom_functions is not None else jmespath_functions.Functions()
        self.dict_cls = options.dict_cls if options.dict_cls is not None else dict

    def node(self, node: dict[str, Any]) -> Compiled:
        method = getattr(self, f"_{node['type']}", None)
        if method is None:
            raise Unsupported(node["type"])
        return method(node)

    # -- leaves

    def _field(self, node: dict[str, Any]) -> Compiled:
        key = node["value"]

        def field(value: Any) -> Any:
            try:
                return value.get(key)
            except AttributeError:
                return None

        return field

    def _current(self, node: dict[str, Any]) -> Compiled:
        return _identity

    def _identity(self, node: dict[str, Any]) -> Compiled:
        return _identity

    def _literal(self, node: dict[str, Any]) -> Compiled:
        constant = node["value"]
        return lambda value: constant

    def _index(self, node: dict[str, Any]) -> Compiled:
        position = node["value"]

        def index(value: Any) -> Any:
            if not isinstance(value, list):
                return None
            try:
                return value[position]
            except IndexError:
                return None

        return index

    def _slice(self, node: dict[str, Any]) -> Compiled:
        children = node["children"]

        def slice_(value: Any) -> Any:
            if not isinstance(value, list):
                return None
            return value[slice(*children)]

        return slice_

    def _expref(self, node: dict[str, Any]) -> Compiled:
        expression = node["children"][0]
        reference = _Expression(expression, self.node(expression), self.options)
        return lambda value: reference

    # -- chains

    def _subexpression(self, node: dict[str, Any]) -> Compiled:
        children = node["children"]
        if all(child["type"] == "field" for child in children):
            keys = tuple(child["value"] for child in children)

            def path(value: Any) -> Any:
                for key in keys:
                    try:
                        value = value.get(key)
                    except AttributeError:
                        return None  # None.get: every later field is None too
                return value

            return path
        return self._chain([self.node(child) for child in children])

    _index_expression = _subexpression
    _pipe = _subexpression

    @staticmethod
    def _chain(steps: list[Compiled]) -> Compiled:
        if len(steps) == 1:
            return steps[0]
        if len(steps) == 2:
            first, second = steps
            return lambda value: second(first(value))

        def chain(value: Any) -> Any:
            for step in steps:
                value = step(value)
            return value

        return chain

    # -- collections

    def _multi_select_dict(self, node: dict[str, Any]) -> Compiled:
        pairs = tuple((child["value"], self.node(child["children"][0])) for child in node["children"])
        dict_cls = self.dict_cls
        if dict_cls is dict:

            def multi_select_dict(value: Any) -> Any:
                if value is None:
                    return None
                return {key: item(value) for key, item in pairs}

            return multi_select_dict

        def multi_select_custom(value: Any) -> Any:
            if value is None:
                return None
            collected: dict[Any, Any] = dict_cls()
            for key, item in pairs:
                collected[key] = item(value)
            return collected

        return multi_select_custom

    def _multi_select_list(self, node: dict[str, Any]) -> Compiled:
        items = tuple(self.node(child) for child in node["children"])

        def multi_select_list(value: Any) -> Any:
            if value is None:
                return None
            return [item(value) for item in items]

        return multi_select_list

    def _projection(self, node: dict[str, Any]) -> Compiled:
        left, right = (self.node(child) for child in node["children"])
        if right is _identity:

            def list_projection(value: Any) -> Any:
                base = left(value)
                if not isinstance(base, list):
                    return None
                return [element for element in base if element is not None]

            return list_projection

        def projection(value: Any) -> Any:
            base = left(value)
            if not isinstance(base, list):
                return None
            return _project(right, base)

        return projection

    def _value_projection(self, node: dict[str, Any]) -> Compiled:
        left, right = (self.node(child) for child in node["children"])

        def value_projection(value: Any) -> Any:
            base = left(value)
            try:
                base = base.values()
            except AttributeError:
                return None
            return _project(right, base)

        return value_projection

    def _filter_projection(self, node: dict[str, Any]) -> Compiled:
        left, right, condition = (self.node(child) for child in node["children"])

        def filter_projection(value: Any) -> Any:
            base = left(value)
            if not isinstance(base, list):
                return None
            collected = []
            for element in base:
                if not _is_false(condition(element)):
                    current = right(element)
                    if current is not None:
                        collected.append(current)
            return collected

        return filter_projection

    def _flatten(self, node: dict[str, Any]) -> Compiled:
        inner = self.node(node["children"][0])

        def flatten(value: Any) -> Any:
            base = inner(value)
            if not isinstance(base, list):
                return None
            merged = []
            for element in base:
                if isinstance(element, list):
                    merged.extend(element)
                else:
                    merged.append(element)
            return merged

        return flatten

    # -- logic

    def _comparator(self, node: dict[str, Any]) -> Compiled:
        left, right = (self.node(child) for child in node["children"])
        operation = node["value"]
        if operation == "eq":
            return lambda value: _equals(left(value), right(value))
        if operation == "ne":
            return lambda value: not _equals(left(value), right(value))
        compare = {"lt": operator.lt, "gt": operator.gt, "lte": operator.le, "gte": operator.ge}.get(operation)
        if compare is None:
            raise Unsupported(f"comparator {operation}")

        def ordering(value: Any) -> Any:
            a = left(value)
            b = right(value)
            if not (_is_comparable(a) and _is_comparable(b)):
                return None
            return compare(a, b)

        return ordering

    def _or_expression(self, node: dict[str, Any]) -> Compiled:
        left, right = (self.node(child) for child in node["children"])

        def or_expression(value: Any) -> Any:
            matched = left(value)
            if _is_false(matched):
                matched = right(value)
            return matched

        return or_expression

    def _and_expression(self, node: dict[str, Any]) -> Compiled:
        left, right = (self.node(child) for child in node["children"])

        def and_expression(value: Any) -> Any:
            matched = left(value)
            if _is_false(matched):
                return matched
            return right(value)

        return and_expression

    def _not_expression(self, node: dict[str, Any]) -> Compiled:
        inner = self.node(node["children"][0])

        def not_expression(value: Any) -> Any:
            original = inner(value)
            if _is_actual_number(original) and original == 0:
                return False  # JMESPath: !0 is false, 0 is not falsy
            return not original

        return not_expression

    # -- functions

    def _function_expression(self, node: dict[str, Any]) -> Compiled:
        name = node["value"]
        if name in self.overrides:
            return self.overrides[name](node, self.node)
        arguments = tuple(self.node(child) for child in node["children"])
        table = self.functions
        spec = table.FUNCTION_TABLE.get(name)
        if spec is None:  # jmespath reports an unknown function when it is called, after its arguments

            def unknown(value: Any) -> Any:
                return table.call_function(name, [argument(value) for argument in arguments])

            return unknown
        function, signature = spec["function"], spec["signature"]
        check = _argument_check(table, name, signature, len(arguments))
        if len(arguments) == 1:
            (only,) = arguments
            allowed = _plain_types(table, signature)
            if allowed is not None:  # a value of an allowed type needs no check: no list, no call

                def call1_typed(value: Any) -> Any:
                    resolved = only(value)
                    if type(resolved).__name__ not in allowed:
                        check([resolved])
                    return function(table, resolved)

                return call1_typed

            def call1(value: Any) -> Any:
                resolved = [only(value)]
                check(resolved)
                return function(table, resolved[0])

            return call1

        def call(value: Any) -> Any:
            resolved = [argument(value) for argument in arguments]
            check(resolved)
            return function(table, *resolved)

        return call


def _plain_types(table: Any, signature: list[dict[str, Any]]) -> frozenset[str] | None:
    """The Python type names a function of one plain-typed argument (``number``, not
    ``array-number``) takes without a check, or None where :func:`_argument_check` must see
    every value. The MAVLink position route calls ten such functions per message; the list
    and the call of the general check were a third of its mapping's time (bench/throughput.py)."""
    if len(signature) != 1 or signature[0].get("variadic") or not signature[0]["types"] or _checks_overridden(table):
        return None
    allowed, subtypes = table._get_allowed_pytypes(signature[0]["types"])
    return None if subtypes else frozenset(allowed)


def _checks_overridden(table: Any) -> bool:
    base = jmespath_functions.Functions
    return any(
        getattr(type(table), method) is not getattr(base, method)
        for method in ("_validate_arguments", "_type_check", "_type_check_single", "_get_allowed_pytypes")
    )


def _argument_check(table: Any, name: str, signature: list[dict[str, Any]], count: int) -> Callable[[list[Any]], None]:
    """jmespath's ``Functions._validate_arguments`` with what depends only on the expression
    done once: the arity (known from the call's text) and each argument's allowed Python
    type names. A value of another type, or an argument with element types (``array-number``),
    goes through jmespath's own check, which raises its usual error or passes."""
    overridden = _checks_overridden(table)
    if signature and signature[-1].get("variadic"):
        arity_ok = count >= len(signature)
    else:
        arity_ok = count == len(signature)
    if overridden or not arity_ok:
        validate = table._validate_arguments
        return lambda resolved: validate(resolved, signature, name)
    checks = []
    for index, entry in enumerate(signature):
        types = entry["types"]
        if not types:
            continue
        allowed, subtypes = table._get_allowed_pytypes(types)
        checks.append((index, frozenset(allowed), bool(subtypes), types))
    if not checks:
        return lambda resolved: None
    check_single = table._type_check_single

    def check(resolved: list[Any]) -> None:
        for index, allowed, has_subtypes, types in checks:
            current = resolved[index]
            if has_subtypes or type(current).__name__ not in allowed:
                check_single(current, types, name)

    return check

__all__ = ["Compiled", "Unsupported", "compile_parsed", "is_compiled"]
