"""One pass over the YAML node tree against the config's msgspec schema.

Every problem is collected with its key path and YAML line; nothing stops at the first. Values
are built bottom-up: each section is converted by msgspec from its already-checked fields, which
runs the section's own `__post_init__` exactly once. A value that is wrong only drops its own
section; its siblings are still checked.
"""

from __future__ import annotations

import operator
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import msgspec
import msgspec.inspect as mi
import yaml
from yaml.constructor import ConstructorError, SafeConstructor

from ._errors import ConfigIssue
from ._model import field_check

MAP_TAG = "tag:yaml.org,2002:map"
STR_TAG = "tag:yaml.org,2002:str"
INT_TAG = "tag:yaml.org,2002:int"
_SEQ_TAG = "tag:yaml.org,2002:seq"
_NUMBER_TAGS = (INT_TAG, "tag:yaml.org,2002:float")
_NULL_TAG = "tag:yaml.org,2002:null"
_MERGE_TAG = "tag:yaml.org,2002:merge"
_PLAINTEXT_KEYS = ("token", "auth_token", "password", "secret")
_BOUNDS = (
    ("gt", ">", operator.gt),
    ("ge", ">=", operator.ge),
    ("lt", "<", operator.lt),
    ("le", "<=", operator.le),
)
_SCALARS = (mi.StrType, mi.IntType, mi.FloatType, mi.BoolType, mi.LiteralType, mi.NoneType)
# msgspec's names for kinds of value, in its messages ("Expected `int`, got `str`").
_TYPE_NAMES: dict[type, str] = {
    mi.StrType: "str",
    mi.IntType: "int",
    mi.FloatType: "float",
    mi.BoolType: "bool",
    mi.NoneType: "null",
    mi.StructType: "object",
    mi.DictType: "object",
    mi.ListType: "array",
    mi.TupleType: "array",
}
_KINDS: dict[type, str] = {type(None): "null", bool: "bool", int: "int", float: "float", str: "str"}


class _Invalid:
    """Marks a value that has been reported; whatever contains it is not built."""


INVALID: Any = _Invalid()


@dataclass(frozen=True)
class Where:
    """A value's key path (`$.a.b[2]`) and the YAML line of its key or list item."""

    path: str
    line: int | None

    def key(self, name: str, line: int | None) -> Where:
        return Where(f"{self.path}.{name}", line)

    def item(self, index: int, line: int | None) -> Where:
        return Where(f"{self.path}[{index}]", line)


def line_of(node: yaml.Node) -> int | None:
    """1-based; None for a node that did not come from the file (an environment fallback)."""
    return None if node.start_mark is None else node.start_mark.line + 1


def key_text(node: yaml.Node) -> str:
    return node.value if isinstance(node, yaml.ScalarNode) else f"<{_kind_of_node(node)}>"


def mapping_pairs(
    node: yaml.MappingNode, merging: frozenset[int] = frozenset()
) -> list[tuple[yaml.Node, yaml.Node]]:
    """A mapping's entries with `<<` merges applied as YAML does, leaving the tree as it is.

    A key of the mapping itself beats a merged one; of several merged, the first source wins.
    A key the mapping itself gives twice is an error: which of its values counts would be a
    guess (two `ros2:` blocks, say, of which one would vanish without a word).
    """
    if id(node) in merging:
        raise ConstructorError(None, None, "a `<<` merge includes itself", node.start_mark)
    merging |= {id(node)}
    entries: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    own: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    for key, value in node.value:
        if key.tag == _MERGE_TAG:
            for source in reversed(_merge_sources(value)):
                entries |= {key_text(k): (k, v) for k, v in mapping_pairs(source, merging)}
        else:
            name = key_text(key)
            if name in own:
                first = own[name][0].start_mark.line + 1
                raise ConstructorError(None, None, f"repeated key `{name}` (first on line "
                                       f"{first}): which value counts would be a guess",
                                       key.start_mark)
            own[name] = (key, value)
    return list((entries | own).values())


def _merge_sources(node: yaml.Node) -> list[yaml.MappingNode]:
    sources = node.value if isinstance(node, yaml.SequenceNode) else [node]
    if not all(isinstance(source, yaml.MappingNode) for source in sources):
        msg = "a `<<` merge takes a mapping or a list of mappings"
        raise ConstructorError(None, None, msg, node.start_mark)
    return list(sources)


class Walker:
    """Checks YAML nodes against msgspec type info; `issues` holds what was wrong."""

    def __init__(self) -> None:
        self.issues: list[ConfigIssue] = []
        self._constructor = SafeConstructor()

    def value(self, node: yaml.Node, info: mi.Type, at: Where) -> Any:
        """The converted value, or INVALID after recording why."""
        if isinstance(info, mi.Metadata):
            return self._checked(node, info, at)
        if isinstance(info, mi.StructType):
            return self._struct(node, info, at)
        if isinstance(info, mi.DictType):
            return self._dict(node, info, at)
        if isinstance(info, (mi.ListType, mi.TupleType)):
            return self._array(node, info, at)
        if isinstance(info, mi.UnionType):
            return self._union(node, info, at)
        if isinstance(info, _SCALARS):
            return self._scalar(node, info, at)
        return self._construct(node, at)  # a type this walk does not know: msgspec judges it

    def fail(self, at: Where, message: str) -> Any:
        self.issues.append(ConfigIssue(at.path, at.line, message))
        return INVALID

    def _checked(self, node: yaml.Node, info: mi.Metadata, at: Where) -> Any:
        value = self.value(node, info.type, at)
        problem_of = field_check(info)
        if value is INVALID or problem_of is None:
            return value
        problem = problem_of(value)
        return value if problem is None else self.fail(at, problem)

    def _struct(self, node: yaml.Node, info: mi.StructType, at: Where) -> Any:
        pairs = self._pairs(node, info, at)
        if pairs is None:
            return INVALID
        fields = {field.encode_name: field for field in info.fields}
        values: dict[str, Any] = {}
        for key, value_node in pairs:
            name = key_text(key)
            where = at.key(name, line_of(key))
            if name in _PLAINTEXT_KEYS:
                self.fail(where, "plaintext secrets are not allowed; use token_env or token_sha256")
            elif name not in fields or key.tag != STR_TAG:
                self.fail(where, _unknown_key(name, fields))
            else:
                values[name] = self.value(value_node, fields[name].type, where)
        missing = [f.encode_name for f in info.fields if f.required and f.encode_name not in values]
        for name in missing:
            self.fail(at.key(name, at.line), "missing required key")
        if missing or _any_invalid(values.values()):
            return INVALID
        return self._build(values, info.cls, at)

    def _build(self, values: dict[str, Any], cls: type[msgspec.Struct], at: Where) -> Any:
        """msgspec converts the checked fields and runs the section's `__post_init__`."""
        try:
            return msgspec.convert(values, cls)
        except msgspec.ValidationError as exc:
            return self.fail(at, str(exc))

    def _dict(self, node: yaml.Node, info: mi.DictType, at: Where) -> Any:
        pairs = self._pairs(node, info, at)
        if pairs is None:
            return INVALID
        problem = _length_problem(len(pairs), info, "object")
        if problem is not None:
            self.fail(at, problem)
        entries = [self._entry(key, value, info, at) for key, value in pairs]
        if problem is not None or _any_invalid(part for entry in entries for part in entry):
            return INVALID
        return dict(entries)

    def _entry(
        self, key: yaml.Node, value: yaml.Node, info: mi.DictType, at: Where
    ) -> tuple[Any, Any]:
        where = at.key(key_text(key), line_of(key))
        return self.value(key, info.key_type, where), self.value(value, info.value_type, where)

    def _array(self, node: yaml.Node, info: mi.ListType | mi.TupleType, at: Where) -> Any:
        if not isinstance(node, yaml.SequenceNode) or node.tag != _SEQ_TAG:
            return self._wrong_kind(node, info, at)
        if isinstance(info, mi.TupleType):
            item_types = info.item_types
        else:
            item_types = (info.item_type,) * len(node.value)
        problem = _length_problem(len(node.value), info, "array")
        if problem is not None:
            self.fail(at, problem)
        out = [
            self.value(item, item_type, at.item(index, line_of(item)))
            for index, (item, item_type) in enumerate(zip(node.value, item_types, strict=False))
        ]
        if problem is not None or _any_invalid(out):
            return INVALID
        return tuple(out) if isinstance(info, mi.TupleType) else out

    def _union(self, node: yaml.Node, info: mi.UnionType, at: Where) -> Any:
        members = [t for t in info.types if not isinstance(t, mi.NoneType)]
        if len(members) < len(info.types) and is_null(node):
            return None
        fitting = [t for t in members if _fits(node, t)]
        if len(fitting) == 1:
            return self.value(node, fitting[0], at)
        for member in fitting:  # several scalar kinds: the first that takes the value wins
            trial = Walker()
            value = trial.value(node, member, at)
            if not trial.issues:
                return value
        return self._wrong_kind(node, info, at)

    def _scalar(self, node: yaml.Node, info: mi.Type, at: Where) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            return self._wrong_kind(node, info, at)
        value = self._construct(node, at)
        if value is INVALID:
            return INVALID
        if node.tag in _NUMBER_TAGS and _expected(info) != "str":
            misread = _misread_number(node.value)
            if misread is not None:
                return self.fail(at, f"YAML reads the unquoted {node.value} as {value!r} "
                                 f"({misread}); write the number itself")
        value, problem = _scalar_problem(value, info)
        if problem is not None and _expected(info) == "str" and node.style is None:
            # `kid: 12345678` (an SDK key id that happens to be all digits), `name: yes`, ...
            read_as = {"int": "a number", "float": "a number", "bool": "a boolean"}.get(
                _kind_of(value), _kind_of(value))
            problem += (f": YAML reads the unquoted {node.value} as {read_as}; "
                        f"quote it ('{node.value}') to mean the text")
        elif problem is not None and isinstance(value, str) and _read_as_text(node):
            problem += _number_as_text(value)
        return value if problem is None else self.fail(at, problem)

    def _construct(self, node: yaml.Node, at: Where) -> Any:
        try:
            return self._constructor.construct_object(node, deep=True)
        except (yaml.YAMLError, ValueError, KeyError, RecursionError) as exc:
            return self.fail(at, f"not valid YAML: {exc}")

    def _pairs(
        self, node: yaml.Node, info: mi.Type, at: Where
    ) -> list[tuple[yaml.Node, yaml.Node]] | None:
        if not isinstance(node, yaml.MappingNode) or node.tag != MAP_TAG:
            self._wrong_kind(node, info, at)
            return None
        try:
            return mapping_pairs(node)
        except yaml.YAMLError as exc:  # a broken `<<` merge
            self.fail(at, f"not valid YAML: {exc}")
            return None

    def _wrong_kind(self, node: yaml.Node, info: mi.Type, at: Where) -> Any:
        if isinstance(node, yaml.ScalarNode):
            value = self._construct(node, at)
            if value is INVALID:
                return INVALID
            got = _kind_of(value)
        elif node.tag not in (MAP_TAG, _SEQ_TAG):
            return self.fail(at, f"unsupported YAML tag {node.tag!r}")
        else:
            got = _kind_of_node(node)
        return self.fail(at, f"Expected `{_expected(info)}`, got `{got}`")


def _unknown_key(name: str, fields: dict[str, Any]) -> str:
    import difflib  # here: an error's hint, not worth its memory in a process that runs

    close = difflib.get_close_matches(name, fields, n=1)
    return "unknown key" + (f"; did you mean `{close[0]}`?" if close else "")


def _misread_number(text: str) -> str | None:
    """How YAML 1.1 reads a plain number other than its digits say, or None.

    Base 60 (`1:5` is 65) and a leading zero's octal (`010` is 8): nobody writes a limit so
    meaning that, and a typo must not load as a number far from any reading of it. `0x10`
    says what it is and stays.
    """
    if ":" in text:
        return "a base 60 number"
    if re.fullmatch(r"[-+]?0[0-7_]+", text):
        return "octal, for its leading zero"
    return None


def _read_as_text(node: yaml.ScalarNode) -> bool:
    """Whether YAML itself made a plain scalar text (`1e3`), not a `!!str` tag: `!!str 1.0`
    was told its 1.0 needs a dot."""
    if node.style is not None:
        return False
    resolver = yaml.resolver.Resolver()  # SafeLoader's: the same implicit rules
    implicit = resolver.resolve(yaml.ScalarNode, node.value, (True, False))  # type: ignore[no-untyped-call]
    return bool(implicit == STR_TAG)


def _number_as_text(text: str) -> str:
    """Why a plain value that looks like a number is text (`1e3`), or nothing to add."""
    if not re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", text):
        return ""  # `nan`, `inf` too are text, but no digits of a number were meant
    return (f": YAML reads the unquoted {text} as text (its floats need a dot and a signed "
            "exponent: write 1.0e+3, not 1e3)")


def _fits(node: yaml.Node, info: mi.Type) -> bool:
    """Whether a node is of the kind (object, array, scalar) a type reads."""
    if isinstance(info, mi.Metadata):
        return _fits(node, info.type)
    if isinstance(info, (mi.StructType, mi.DictType)):
        return isinstance(node, yaml.MappingNode)
    if isinstance(info, (mi.ListType, mi.TupleType)):
        return isinstance(node, yaml.SequenceNode)
    return isinstance(node, yaml.ScalarNode) or not isinstance(info, _SCALARS)


def is_null(node: yaml.Node) -> bool:
    return isinstance(node, yaml.ScalarNode) and node.tag == _NULL_TAG


def _any_invalid(values: Iterable[Any]) -> bool:
    return any(value is INVALID for value in values)


def _length_problem(
    length: int, info: mi.ListType | mi.TupleType | mi.DictType | mi.StrType, kind: str
) -> str | None:
    if isinstance(info, mi.TupleType):
        expected = len(info.item_types)
        return None if length == expected else f"Expected `{kind}` of length {expected}"
    if info.min_length is not None and length < info.min_length:
        return f"Expected `{kind}` of length >= {info.min_length}"
    if info.max_length is not None and length > info.max_length:
        return f"Expected `{kind}` of length <= {info.max_length}"
    return None


def _scalar_problem(value: Any, info: mi.Type) -> tuple[Any, str | None]:
    """The value as msgspec converts it (an int for a float becomes a float), and any problem."""
    if isinstance(info, mi.LiteralType):
        return value, _literal_problem(value, info)
    expected = _expected(info)
    if _kind_of(value) != expected and not (expected == "float" and _kind_of(value) == "int"):
        return value, f"Expected `{expected}`, got `{_kind_of(value)}`"
    if isinstance(info, mi.FloatType):
        try:
            value = float(value)
        except OverflowError:
            return value, "Number out of range"
    if isinstance(info, (mi.IntType, mi.FloatType)):
        return value, _number_problem(value, info)
    if isinstance(info, mi.StrType):
        return value, _str_problem(value, info)
    return value, None


def _literal_problem(value: Any, info: mi.LiteralType) -> str | None:
    if any(type(value) is type(allowed) and value == allowed for allowed in info.values):
        return None
    kinds = {_kind_of(allowed) for allowed in info.values}
    if _kind_of(value) not in kinds:
        return f"Expected `{' | '.join(sorted(kinds))}`, got `{_kind_of(value)}`"
    allowed = ", ".join(repr(v) for v in info.values)
    return f"Invalid enum value {value!r} (expected one of {allowed})"


def _number_problem(value: float, info: mi.IntType | mi.FloatType) -> str | None:
    kind = _expected(info)
    for attr, symbol, holds in _BOUNDS:
        bound = getattr(info, attr)
        if bound is not None and not holds(value, bound):  # NaN holds no bound
            return f"Expected `{kind}` {symbol} {bound!r}, got {value!r}"
    if info.multiple_of is not None and value % info.multiple_of != 0:
        return f"Expected `{kind}` that is a multiple of {info.multiple_of!r}, got {value!r}"
    return None


def _str_problem(value: str, info: mi.StrType) -> str | None:
    problem = _length_problem(len(value), info, "str")
    if problem is None and info.pattern is not None and not re.search(info.pattern, value):
        return f"Expected `str` matching regex {info.pattern!r}"
    return problem


def _expected(info: mi.Type) -> str:
    if isinstance(info, mi.Metadata):
        return _expected(info.type)
    if isinstance(info, mi.UnionType):
        return " | ".join(_expected(t) for t in info.types)
    if isinstance(info, mi.LiteralType):
        return " | ".join(sorted({_kind_of(v) for v in info.values}))
    return _TYPE_NAMES.get(type(info), type(info).__name__)


def _kind_of(value: Any) -> str:
    return _KINDS.get(type(value), type(value).__name__)


def _kind_of_node(node: yaml.Node) -> str:
    if isinstance(node, yaml.MappingNode):
        return "object"
    return "array" if isinstance(node, yaml.SequenceNode) else "scalar"
