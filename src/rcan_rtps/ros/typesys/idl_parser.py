"""Parse the ROS dialect of OMG IDL into the neutral type model.

Accepts both the bundle's hand-written files and the rosidl-generated `.idl` files any
ROS install ships under `share/<pkg>/`: modules, structs, `typedef` arrays, member array
declarators, `sequence<T[, N]>`, `string<N>`, `<Name>_Constants` modules and the
`@default`/`@verbatim`/`@key`/`@unit` annotations. Every error names file and line.
"""

from __future__ import annotations

import ast
import re

import msgspec

from ..errors import IdlSyntaxError
from .model import (
    INTEGER_RANGES,
    Collection,
    Constant,
    ConstValue,
    Field,
    FieldType,
    MessageType,
    ParsedFile,
    Primitive,
)

_TOKEN = re.compile(
    r"""
    (?P<ws>[ \t\r\n]+)
  | (?P<comment>//[^\n]*|/\*.*?\*/)
  | (?P<pp>\#[^\n]*)
  | (?P<string>L?"(?:\\.|[^"\\\n])*")
  | (?P<char>L?'(?:\\.|[^'\\\n])*')
  | (?P<number>0[xX][0-9a-fA-F]+|(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)
  | (?P<ident>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<scope>::)
  | (?P<punct>[{}();<>,=\[\]@+\-])
    """,
    re.VERBOSE | re.DOTALL,
)

# IDL spellings of primitive types, including the multi-word C-like ones.
_PRIMITIVE_WORDS: dict[tuple[str, ...], Primitive] = {
    ("boolean",): Primitive.BOOLEAN,
    ("octet",): Primitive.OCTET,
    ("char",): Primitive.CHAR,
    ("wchar",): Primitive.WCHAR,
    ("int8",): Primitive.INT8,
    ("uint8",): Primitive.UINT8,
    ("int16",): Primitive.INT16,
    ("uint16",): Primitive.UINT16,
    ("int32",): Primitive.INT32,
    ("uint32",): Primitive.UINT32,
    ("int64",): Primitive.INT64,
    ("uint64",): Primitive.UINT64,
    ("short",): Primitive.INT16,
    ("unsigned", "short"): Primitive.UINT16,
    ("long",): Primitive.INT32,
    ("unsigned", "long"): Primitive.UINT32,
    ("long", "long"): Primitive.INT64,
    ("unsigned", "long", "long"): Primitive.UINT64,
    ("float",): Primitive.FLOAT,
    ("double",): Primitive.DOUBLE,
    ("long", "double"): Primitive.LONG_DOUBLE,
    ("string",): Primitive.STRING,
    ("wstring",): Primitive.WSTRING,
}
_MAX_WORDS = 3


class _Tok(msgspec.Struct):
    kind: str
    text: str
    line: int


def _tokenize(text: str, path: str) -> list[_Tok]:
    tokens: list[_Tok] = []
    pos, line = 0, 1
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise IdlSyntaxError(path, line, f"unexpected character {text[pos]!r}")
        kind = m.lastgroup or ""
        chunk = m.group()
        if kind not in ("ws", "comment"):
            tokens.append(_Tok(kind, chunk, line))
        line += chunk.count("\n")
        pos = m.end()
    return tokens


def _unquote(literal: str) -> str:
    body = literal[1:] if literal.startswith("L") else literal
    return str(ast.literal_eval(body))


class _Parser:
    def __init__(self, text: str, path: str) -> None:
        self.path = path
        self.toks = _tokenize(text, path)
        self.i = 0
        self.result = ParsedFile(path)
        self.typedefs: dict[str, FieldType] = {}  # scoped name → type
        self.pending_constants: dict[str, list[Constant]] = {}

    # -- token helpers ------------------------------------------------------
    def _peek(self, ahead: int = 0) -> _Tok | None:
        j = self.i + ahead
        return self.toks[j] if j < len(self.toks) else None

    def _line(self) -> int:
        tok = self._peek()
        return tok.line if tok else (self.toks[-1].line if self.toks else 1)

    def _error(self, message: str) -> IdlSyntaxError:
        return IdlSyntaxError(self.path, self._line(), message)

    def _next(self) -> _Tok:
        tok = self._peek()
        if tok is None:
            raise self._error("unexpected end of file")
        self.i += 1
        return tok

    def _expect(self, text: str) -> _Tok:
        tok = self._next()
        if tok.text != text:
            self.i -= 1
            raise self._error(f"expected {text!r}, found {tok.text!r}")
        return tok

    def _accept(self, text: str) -> bool:
        tok = self._peek()
        if tok is not None and tok.text == text:
            self.i += 1
            return True
        return False

    def _ident(self) -> str:
        tok = self._next()
        if tok.kind != "ident":
            self.i -= 1
            raise self._error(f"expected a name, found {tok.text!r}")
        return tok.text

    def _int(self) -> int:
        tok = self._next()
        if tok.kind != "number":
            self.i -= 1
            raise self._error(f"expected a whole number, found {tok.text!r}")
        try:
            return int(tok.text, 0)
        except ValueError:
            self.i -= 1
            raise self._error(f"expected a whole number, found {tok.text!r}") from None

    def _positive(self, what: str) -> int:
        size = self._int()
        if size <= 0:
            self.i -= 1
            raise self._error(f"{what} must be a positive number, found {size}")
        return size

    # -- grammar --------------------------------------------------------------
    def parse(self) -> ParsedFile:
        while self._peek() is not None:
            tok = self._peek()
            assert tok is not None
            if tok.kind == "pp":
                self._preprocessor(self._next())
            elif tok.text == "module":
                self._module([])
            elif tok.text == "@":
                self._annotations()
            else:
                raise self._error(f"expected 'module' or '#include', found {tok.text!r}")
        if self.pending_constants:
            owner = next(iter(self.pending_constants))
            raise self._error(f"constants module for {owner!r} has no matching struct")
        return self.result

    def _preprocessor(self, tok: _Tok) -> None:
        m = re.match(r'#\s*include\s*[<"]([^>"]+)[>"]', tok.text)
        if m:
            self.result.includes.append(m.group(1))
        elif not re.match(r"#\s*(pragma|ifndef|define|endif|ifdef)\b", tok.text):
            raise IdlSyntaxError(self.path, tok.line, f"unsupported directive {tok.text!r}")

    def _module(self, scope: list[str]) -> None:
        self._expect("module")
        name = self._ident()
        self._expect("{")
        inner = [*scope, name]
        if name.endswith("_Constants") and len(scope) >= 2:
            self._constants_module(scope, name[: -len("_Constants")])
            return
        while not self._accept("}"):
            annotations = self._annotations()
            tok = self._peek()
            if tok is None:
                raise self._error(f"module {name!r} is not closed")
            if tok.text == "module":
                self._module(inner)
            elif tok.text == "struct":
                self._struct(inner, annotations)
            elif tok.text == "typedef":
                self._typedef(inner)
            elif tok.text == "const":
                raise self._error("constants must sit in a '<Struct>_Constants' module")
            else:
                raise self._error(f"expected module, struct or typedef, found {tok.text!r}")
        self._expect(";")

    def _constants_module(self, scope: list[str], owner: str) -> None:
        constants: list[Constant] = []
        while not self._accept("}"):
            self._annotations()
            self._expect("const")
            ftype = self._type_spec(scope)
            name = self._ident()
            self._expect("=")
            value = self._literal(ftype)
            self._expect(";")
            constants.append(Constant(name, ftype, value))
        self._expect(";")
        full = self._ros_name([*scope, owner])
        self.pending_constants.setdefault(full, []).extend(constants)
        existing = self.result.structs.get(full)
        if existing is not None:
            self._attach_constants(existing)

    def _attach_constants(self, struct: MessageType) -> None:
        extra = self.pending_constants.pop(struct.name, [])
        if extra:
            self.result.structs[struct.name] = MessageType(
                struct.name, struct.fields, (*struct.constants, *extra), struct.source
            )

    def _struct(self, scope: list[str], _annotations: dict[str, str]) -> None:
        line = self._line()
        self._expect("struct")
        name = self._ident()
        full = self._ros_name([*scope, name])
        if self._accept(";"):  # forward declaration
            return
        self._expect("{")
        fields: list[Field] = []
        while not self._accept("}"):
            annotations = self._annotations()
            ftype = self._type_spec(scope)
            fname = self._ident()
            if self._accept("["):
                if ftype.is_collection:
                    raise self._error(f"field {fname!r}: arrays of collections are not ROS types")
                size = self._positive("an array size")
                self._expect("]")
                ftype = FieldType(ftype.primitive, ftype.nested, ftype.string_bound,
                                  Collection.ARRAY, size)
            self._expect(";")
            if any(f.name == fname for f in fields):
                raise self._error(f"field {fname!r} is defined twice in {name!r}")
            default = self._default(annotations.get("default"), ftype, fname)
            fields.append(Field(fname, ftype, default))
        self._expect(";")
        if full in self.result.structs:
            raise IdlSyntaxError(self.path, line, f"struct {full!r} is defined twice")
        self.result.structs[full] = MessageType(full, tuple(fields), (), f"{self.path}:{line}")
        self._attach_constants(self.result.structs[full])

    def _typedef(self, scope: list[str]) -> None:
        self._expect("typedef")
        ftype = self._type_spec(scope)
        name = self._ident()
        if self._accept("["):
            if ftype.is_collection:
                raise self._error(f"typedef {name!r}: arrays of collections are not ROS types")
            size = self._positive("an array size")
            self._expect("]")
            ftype = FieldType(ftype.primitive, ftype.nested, ftype.string_bound,
                              Collection.ARRAY, size)
        self._expect(";")
        self.typedefs["::".join([*scope, name])] = ftype

    def _annotations(self) -> dict[str, str]:
        """Reads `@name` / `@name(args)`; returns the raw `value=` text of each."""
        found: dict[str, str] = {}
        while self._accept("@"):
            name = self._ident()
            value = ""
            if self._accept("("):
                depth, parts = 1, []
                while depth:
                    tok = self._next()
                    if tok.text == "(":
                        depth += 1
                    elif tok.text == ")":
                        depth -= 1
                    if depth:
                        parts.append(tok)
                value = self._annotation_value(parts)
            found[name] = value
        return found

    @staticmethod
    def _annotation_value(parts: list[_Tok]) -> str:
        """The `value=` argument of an annotation, or the sole positional one."""
        for k, tok in enumerate(parts[:-2]):
            if tok.text == "value" and parts[k + 1].text == "=":
                rest = parts[k + 2 :]
                break
        else:
            rest = parts
        texts = []
        for tok in rest:
            if tok.text == ",":
                break
            texts.append(_unquote(tok.text) if tok.kind == "string" else tok.text)
        return "".join(texts)

    def _type_spec(self, scope: list[str]) -> FieldType:
        tok = self._peek()
        if tok is None:
            raise self._error("expected a type")
        if tok.text == "sequence":
            self._next()
            self._expect("<")
            element = self._type_spec(scope)
            if element.is_collection:
                raise self._error("sequences of collections are not ROS types")
            bound = self._positive("a sequence bound") if self._accept(",") else 0
            self._expect(">")
            kind = Collection.BOUNDED_SEQUENCE if bound else Collection.SEQUENCE
            return FieldType(element.primitive, element.nested, element.string_bound, kind, bound)
        words = self._primitive_words()
        if words is not None:
            prim = _PRIMITIVE_WORDS[words]
            bound = 0
            if prim.is_string and self._accept("<"):
                bound = self._positive("a string bound")
                self._expect(">")
            return FieldType(primitive=prim, string_bound=bound)
        return self._scoped_type(scope)

    def _primitive_words(self) -> tuple[str, ...] | None:
        for n in range(_MAX_WORDS, 0, -1):
            words = tuple(t.text for t in self.toks[self.i : self.i + n] if t.kind == "ident")
            if len(words) == n and words in _PRIMITIVE_WORDS:
                self.i += n
                return words
        return None

    def _scoped_type(self, scope: list[str]) -> FieldType:
        parts = [self._ident()]
        while self._accept("::"):
            parts.append(self._ident())
        for depth in range(len(scope), -1, -1):  # innermost scope first
            key = "::".join([*scope[:depth], *parts])
            if key in self.typedefs:
                return self.typedefs[key]
        if len(parts) == 1:
            parts = [*scope, parts[0]]
        if len(parts) != 3:
            raise self._error(f"type {'::'.join(parts)!r} is not of the form pkg::kind::Name")
        return FieldType(nested="/".join(parts))

    def _ros_name(self, parts: list[str]) -> str:
        if len(parts) != 3:
            raise self._error(
                f"struct {'::'.join(parts)!r} must sit in 'module <pkg> {{ module msg|srv|action'"
            )
        return "/".join(parts)

    # -- literals -------------------------------------------------------------
    def _literal(self, ftype: FieldType) -> ConstValue:
        sign = ""
        if self._accept("-"):
            sign = "-"
        elif self._accept("+"):
            pass
        tok = self._next()
        try:
            value = _convert_scalar(sign + tok.text if tok.kind != "string" else tok.text,
                                    ftype, quoted=tok.kind in ("string", "char"))
            _check_fits(value, ftype)
            return value
        except ValueError as exc:
            self.i -= 1
            raise self._error(str(exc)) from None

    def _default(self, raw: str | None, ftype: FieldType, fname: str) -> object:
        if raw is None:
            return None
        try:
            if ftype.is_collection:
                items = ast.literal_eval(raw) if raw.strip() else ()
                if not isinstance(items, (tuple, list)):
                    items = (items,)
                values = tuple(_convert_python(v, ftype.element) for v in items)
                _check_length(len(values), ftype)
                for v in values:
                    _check_fits(v, ftype.element)
                return values
            if ftype.primitive is not None and ftype.primitive.is_string:
                _check_fits(raw, ftype)
                return raw
            value = _convert_scalar(raw, ftype, quoted=False)
            _check_fits(value, ftype)
            return value
        except (ValueError, SyntaxError) as exc:
            raise self._error(f"field {fname!r}: bad @default {raw!r}: {exc}") from None


def _convert_scalar(text: str, ftype: FieldType, *, quoted: bool) -> ConstValue:
    prim = ftype.primitive
    if prim is None:
        raise ValueError("constants must have a primitive type")
    if quoted:
        value = _unquote(text)
        return ord(value) if (prim.is_integer or prim is Primitive.WCHAR) and len(value) == 1 \
            else value
    if prim is Primitive.BOOLEAN:
        if text.upper() in ("TRUE", "FALSE"):
            return text.upper() == "TRUE"
        raise ValueError(f"expected TRUE or FALSE, found {text!r}")
    if prim.is_float:
        return float(text)
    if prim.is_string:
        return text
    return int(text, 0)


def _check_fits(value: object, ftype: FieldType) -> None:
    """Raises ValueError unless a constant or default `value` fits its (element) type."""
    prim = ftype.primitive
    if prim is None:
        return
    if prim.is_string:
        if not isinstance(value, str):
            raise ValueError(f"expected a string, found {value!r}")
        if ftype.string_bound and len(value) > ftype.string_bound:
            raise ValueError(f"{value!r} is longer than the bound of {ftype.string_bound}")
    elif prim is Primitive.BOOLEAN:
        if not isinstance(value, bool):
            raise ValueError(f"expected TRUE or FALSE, found {value!r}")
    elif prim in INTEGER_RANGES:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"expected an integer, found {value!r}")
        low, high = INTEGER_RANGES[prim]
        if not low <= value <= high:
            raise ValueError(f"{value} is out of range for {prim.value} [{low}, {high}]")
    elif prim.is_float and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise ValueError(f"expected a number, found {value!r}")


def _check_length(length: int, ftype: FieldType) -> None:
    if ftype.collection is Collection.ARRAY and length != ftype.size:
        raise ValueError(f"expected exactly {ftype.size} items, found {length}")
    if ftype.collection is Collection.BOUNDED_SEQUENCE and length > ftype.size:
        raise ValueError(f"expected at most {ftype.size} items, found {length}")


def _convert_python(value: object, ftype: FieldType) -> object:
    prim = ftype.primitive
    if prim is not None and prim.is_float and isinstance(value, (int, float)):
        return float(value)
    return value


def parse_idl(text: str, path: str = "<idl>") -> ParsedFile:
    """Parses one `.idl` file's text. Raises `IdlSyntaxError` naming file and line."""
    return _Parser(text, path).parse()
