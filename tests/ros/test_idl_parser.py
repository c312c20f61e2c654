"""The IDL parser: the neutral model it builds from bundle files and from small snippets,
and a clear `IdlSyntaxError` (file and line) for malformed input. No ROS needed."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.ros.errors import IdlSyntaxError, WireError
from rcan_rtps.ros.typesys.idl_parser import parse_idl
from rcan_rtps.ros.typesys.model import (
    Collection,
    Constant,
    Field,
    FieldType,
    MessageType,
    Primitive,
)
from rcan_rtps.ros.typesys.store import bundle_dir

pytestmark = pytest.mark.offline

BUNDLE = bundle_dir()
P = Primitive


def _bundle(interface: str) -> dict[str, MessageType]:
    path = BUNDLE / f"{interface}.idl"
    return parse_idl(path.read_text(encoding="utf-8"), str(path)).structs


def _one(body: str, name: str = "S") -> MessageType:
    """Parses `body` inside `module p { module msg { … }; };` and returns struct `name`."""
    structs = parse_idl(f"module p {{ module msg {{\n{body}\n}}; }};").structs
    return structs[f"p/msg/{name}"]


def _types(msg: MessageType) -> list[tuple[str, FieldType]]:
    return [(f.name, f.type) for f in msg.fields]


# -- bundle files ------------------------------------------------------------------------------


def test_every_bundle_file_parses() -> None:
    files = sorted(BUNDLE.rglob("*.idl"))
    assert len(files) > 150
    for path in files:
        parsed = parse_idl(path.read_text(encoding="utf-8"), str(path))
        assert parsed.structs, path
        pkg, kind = path.relative_to(BUNDLE).parts[-3:-1]
        assert all(name.startswith(f"{pkg}/{kind}/") for name in parsed.structs), path


def test_twist_nested_fields() -> None:
    parsed = parse_idl((BUNDLE / "geometry_msgs/msg/Twist.idl").read_text(), "Twist.idl")
    assert parsed.includes == ["geometry_msgs/msg/Vector3.idl"]
    twist = parsed.structs["geometry_msgs/msg/Twist"]
    assert _types(twist) == [
        ("linear", FieldType(nested="geometry_msgs/msg/Vector3")),
        ("angular", FieldType(nested="geometry_msgs/msg/Vector3")),
    ]
    assert twist.constants == ()
    assert twist.dds_name == "geometry_msgs::msg::dds_::Twist_"
    assert twist.source == "Twist.idl:5"


def test_joint_state_unbounded_sequences() -> None:
    js = _bundle("sensor_msgs/msg/JointState")["sensor_msgs/msg/JointState"]
    assert _types(js) == [
        ("header", FieldType(nested="std_msgs/msg/Header")),
        ("name", FieldType(P.STRING, collection=Collection.SEQUENCE)),
        ("position", FieldType(P.DOUBLE, collection=Collection.SEQUENCE)),
        ("velocity", FieldType(P.DOUBLE, collection=Collection.SEQUENCE)),
        ("effort", FieldType(P.DOUBLE, collection=Collection.SEQUENCE)),
    ]


def test_odometry_covariance_is_a_fixed_array() -> None:
    pwc = _bundle("geometry_msgs/msg/PoseWithCovariance")["geometry_msgs/msg/PoseWithCovariance"]
    assert pwc.field("covariance").type == FieldType(P.DOUBLE, collection=Collection.ARRAY, size=36)


def test_battery_state_constants_and_float32() -> None:
    bs = _bundle("sensor_msgs/msg/BatteryState")["sensor_msgs/msg/BatteryState"]
    consts = {c.name: c for c in bs.constants}
    assert len(consts) == 23
    assert consts["POWER_SUPPLY_HEALTH_SAFETY_TIMER_EXPIRE"] == Constant(
        "POWER_SUPPLY_HEALTH_SAFETY_TIMER_EXPIRE", FieldType(P.UINT8), 8
    )
    assert bs.field("voltage").type == FieldType(P.FLOAT)
    assert bs.field("present").type == FieldType(P.BOOLEAN)
    assert bs.field("cell_voltage").type == FieldType(P.FLOAT, collection=Collection.SEQUENCE)


def test_defaults_bounded_strings_and_bounded_sequences() -> None:
    quat = _bundle("geometry_msgs/msg/Quaternion")["geometry_msgs/msg/Quaternion"]
    assert [(f.name, f.default) for f in quat.fields] == [
        ("x", 0.0),
        ("y", 0.0),
        ("z", 0.0),
        ("w", 1.0),
    ]
    nei = _bundle("rmw_dds_common/msg/NodeEntitiesInfo")["rmw_dds_common/msg/NodeEntitiesInfo"]
    assert nei.field("node_name").type == FieldType(P.STRING, string_bound=256)
    pd = _bundle("rcl_interfaces/msg/ParameterDescriptor")["rcl_interfaces/msg/ParameterDescriptor"]
    assert pd.field("read_only").default is False
    assert pd.field("integer_range").type == FieldType(
        nested="rcl_interfaces/msg/IntegerRange", collection=Collection.BOUNDED_SEQUENCE, size=1
    )
    nss = _bundle("sensor_msgs/msg/NavSatStatus")["sensor_msgs/msg/NavSatStatus"]
    assert nss.field("status").default == -2


def test_service_and_action_files_hold_their_parts() -> None:
    srv = _bundle("std_srvs/srv/SetBool")
    assert sorted(srv) == ["std_srvs/srv/SetBool_Request", "std_srvs/srv/SetBool_Response"]
    assert _types(srv["std_srvs/srv/SetBool_Response"]) == [
        ("success", FieldType(P.BOOLEAN)),
        ("message", FieldType(P.STRING)),
    ]
    action = _bundle("nav2_msgs/action/NavigateToPose")
    assert sorted(action) == [
        f"nav2_msgs/action/NavigateToPose_{p}" for p in ("Feedback", "Goal", "Result")
    ]
    result = action["nav2_msgs/action/NavigateToPose_Result"]
    assert [c.name for c in result.constants] == ["NONE"]
    assert action["nav2_msgs/action/NavigateToPose_Feedback"].field(
        "number_of_recoveries"
    ).type == FieldType(P.INT16)


def test_empty_struct_placeholder() -> None:
    empty = _bundle("std_msgs/msg/Empty")["std_msgs/msg/Empty"]
    assert _types(empty) == [("structure_needs_at_least_one_member", FieldType(P.UINT8))]


# -- snippets ----------------------------------------------------------------------------------


def test_all_primitive_spellings() -> None:
    msg = _one("""struct S {
      boolean a; octet b; char c; wchar d; int8 e; uint8 f; int16 g; uint16 h; int32 i;
      uint32 j; int64 k; uint64 l; short m; unsigned short n; long o; unsigned long p;
      long long q; unsigned long long r; float s; double t; long double u; string v;
      wstring w;
    };""")
    assert [f.type.primitive for f in msg.fields] == [
        P.BOOLEAN,
        P.OCTET,
        P.CHAR,
        P.WCHAR,
        P.INT8,
        P.UINT8,
        P.INT16,
        P.UINT16,
        P.INT32,
        P.UINT32,
        P.INT64,
        P.UINT64,
        P.INT16,
        P.UINT16,
        P.INT32,
        P.UINT32,
        P.INT64,
        P.UINT64,
        P.FLOAT,
        P.DOUBLE,
        P.LONG_DOUBLE,
        P.STRING,
        P.WSTRING,
    ]
    assert all(not f.type.is_collection for f in msg.fields)


def test_strings_sequences_and_arrays() -> None:
    msg = _one("""struct S {
      string<8> bounded;
      wstring<4> wide;
      sequence<int32> unbounded_seq;
      sequence<int32, 5> bounded_seq;
      sequence<string<3>, 4> bounded_seq_of_bounded_strings;
      string<5> array_of_bounded_strings[2];
      float grid[0x10];
      sequence<p::msg::T> nested_seq;
    };""")
    assert _types(msg) == [
        ("bounded", FieldType(P.STRING, string_bound=8)),
        ("wide", FieldType(P.WSTRING, string_bound=4)),
        ("unbounded_seq", FieldType(P.INT32, collection=Collection.SEQUENCE)),
        ("bounded_seq", FieldType(P.INT32, collection=Collection.BOUNDED_SEQUENCE, size=5)),
        (
            "bounded_seq_of_bounded_strings",
            FieldType(P.STRING, string_bound=3, collection=Collection.BOUNDED_SEQUENCE, size=4),
        ),
        (
            "array_of_bounded_strings",
            FieldType(P.STRING, string_bound=5, collection=Collection.ARRAY, size=2),
        ),
        ("grid", FieldType(P.FLOAT, collection=Collection.ARRAY, size=16)),
        ("nested_seq", FieldType(nested="p/msg/T", collection=Collection.SEQUENCE)),
    ]
    assert msg.field("bounded_seq_of_bounded_strings").type.ros_spelling() == "string<=3[<=4]"


def test_constants_of_every_kind() -> None:
    msg = _one("""
      module S_Constants {
        const boolean ON = TRUE;
        const int8 LOW = -128;
        const uint64 HIGH = 18446744073709551615;
        const int32 HEX = 0x1F;
        const double PI = 3.14159;
        const float NEG = -2.5e-3;
        const string NAME = "a \\"quoted\\" name";
        const char LETTER = 'A';
      };
      struct S { uint8 x; };""")
    assert [(c.name, c.value) for c in msg.constants] == [
        ("ON", True),
        ("LOW", -128),
        ("HIGH", 2**64 - 1),
        ("HEX", 31),
        ("PI", 3.14159),
        ("NEG", -0.0025),
        ("NAME", 'a "quoted" name'),
        ("LETTER", 65),
    ]
    assert msg.constants[2].type == FieldType(P.UINT64)


def test_constants_module_may_follow_its_struct() -> None:
    msg = _one("struct S { uint8 x; }; module S_Constants { const uint8 A = 1; };")
    assert [c.name for c in msg.constants] == ["A"]


def test_default_annotations() -> None:
    msg = _one("""struct S {
      @default (value=TRUE) boolean flag;
      @default (value=-7) int16 small;
      @default (value=2) double two;
      @default (value="it's") string text;
      @default (value="(1, 2, 3)") int32 three[3];
      @default (value="[0.5, 1]") sequence<float> floats;
      @default (value="('a', 'b')") sequence<string, 2> names;
      uint8 none;
    };""")
    defaults = {f.name: f.default for f in msg.fields}
    assert defaults == {
        "flag": True,
        "small": -7,
        "two": 2.0,
        "text": "it's",
        "three": (1, 2, 3),
        "floats": (0.5, 1.0),
        "names": ("a", "b"),
        "none": None,
    }
    assert isinstance(defaults["two"], float)


def test_other_annotations_are_accepted_and_ignored() -> None:
    msg = _one("""
      @verbatim (language="comment", text="A struct with a key.")
      struct S {
        @key int32 id;
        @unit (value="m/s") @verbatim (language="comment", text="speed") double speed;
      };""")
    assert _types(msg) == [("id", FieldType(P.INT32)), ("speed", FieldType(P.DOUBLE))]


def test_typedefs_resolve_in_scope() -> None:
    msg = _one("""
      typedef double double__9[9];
      typedef p::msg::T t_alias;
      typedef string<10> name_t;
      struct S { double__9 cov; t_alias nested; sequence<name_t> names; };""")
    assert _types(msg) == [
        ("cov", FieldType(P.DOUBLE, collection=Collection.ARRAY, size=9)),
        ("nested", FieldType(nested="p/msg/T")),
        ("names", FieldType(P.STRING, string_bound=10, collection=Collection.SEQUENCE)),
    ]


def test_nested_modules_scoped_and_relative_names() -> None:
    parsed = parse_idl("""
      module a { module msg { struct Inner { int8 v; }; }; };
      module b { module srv {
        struct X_Request { a::msg::Inner inner; X_Response sibling; };
        struct X_Response { boolean ok; };
      }; };""")
    assert sorted(parsed.structs) == ["a/msg/Inner", "b/srv/X_Request", "b/srv/X_Response"]
    req = parsed.structs["b/srv/X_Request"]
    assert _types(req) == [
        ("inner", FieldType(nested="a/msg/Inner")),
        ("sibling", FieldType(nested="b/srv/X_Response")),
    ]


def test_rosidl_generated_style() -> None:
    """The shape rosidl writes into share/<pkg>/msg/*.idl: guards, includes, verbatim."""
    parsed = parse_idl(
        """// generated from rosidl_adapter/resource/msg.idl.em
#ifndef P__MSG__G_IDL
#define P__MSG__G_IDL
#include "builtin_interfaces/msg/Time.idl"
#pragma once

module p {
  module msg {
    typedef uint8 uint8__16[16];
    module G_Constants {
      const uint8 SIZE = 16;
    };
    @verbatim (language="comment", text=
      "A globally unique id." "\\n"
      "Second line.")
    struct G {
      uint8__16 data;

      @verbatim (language="comment", text=
        "When it was made.")
      builtin_interfaces::msg::Time stamp;
    };
  };
};
#endif
""",
        "G.idl",
    )
    assert parsed.includes == ["builtin_interfaces/msg/Time.idl"]
    g = parsed.structs["p/msg/G"]
    assert _types(g) == [
        ("data", FieldType(P.UINT8, collection=Collection.ARRAY, size=16)),
        ("stamp", FieldType(nested="builtin_interfaces/msg/Time")),
    ]
    assert [c.value for c in g.constants] == [16]


def test_comments_and_forward_declarations() -> None:
    msg = _one("""
      struct S;  // forward declaration
      /* a block
         comment */
      struct S { int8 a; /* inline */ int8 b; };""")
    assert [f.name for f in msg.fields] == ["a", "b"]
    assert msg.fields[0] == Field("a", FieldType(P.INT8))


# -- errors ------------------------------------------------------------------------------------

WRAP = "module p {{ module msg {{\n{}\n}}; }};"

BAD = {
    "unclosed struct": WRAP.format("struct S { int8 a;"),
    "missing semicolon": WRAP.format("struct S { int8 a } ;"),
    "missing field name": WRAP.format("struct S { int8; };"),
    "unknown character": WRAP.format("struct S { int8 a$; };"),
    "unterminated string": WRAP.format('module S_Constants { const string A = "x; };'),
    "unsupported directive": "#error nope\n" + WRAP.format("struct S { int8 a; };"),
    "top-level struct": "struct S { int8 a; };",
    "struct two modules deep only": "module p { struct S { int8 a; }; };",
    "struct four modules deep": WRAP.format("module q { struct S { int8 a; }; };"),
    "type not pkg::kind::Name": WRAP.format("struct S { p::T a; };"),
    "field defined twice": WRAP.format("struct S { int8 a; int16 a; };"),
    "struct defined twice": WRAP.format("struct S { int8 a; }; struct S { int8 b; };"),
    "array of sequences": WRAP.format("struct S { sequence<int8> a[3]; };"),
    "sequence of sequences": WRAP.format("struct S { sequence<sequence<int8>> a; };"),
    "non-integer array size": WRAP.format("struct S { int8 a[1.5]; };"),
    "negative string bound": WRAP.format("struct S { string<-1> a; };"),
    "bound on a non-string": WRAP.format("struct S { int32<4> a; };"),
    "const outside a constants module": WRAP.format("const int8 A = 1; struct S { int8 a; };"),
    "constants without struct": WRAP.format("module S_Constants { const int8 A = 1; };"),
    "non-primitive constant": WRAP.format(
        "module S_Constants { const p::msg::T A = 1; }; struct S { int8 a; };"
    ),
    "boolean constant not TRUE/FALSE": WRAP.format(
        "module S_Constants { const boolean A = 1; }; struct S { int8 a; };"
    ),
    "bad integer default": WRAP.format("struct S { @default (value=1.5) int32 a; };"),
    "bad float default": WRAP.format("struct S { @default (value=abc) double a; };"),
    "bad array default": WRAP.format('struct S { @default (value="(1, 2") int32 a[2]; };'),
    "unclosed annotation": WRAP.format("struct S { @default (value=1 int32 a; };"),
    "end of file in module": "module p { module msg {",
    # checks added with these tests
    "typedef array of a sequence": WRAP.format("typedef sequence<int32> T[3]; struct S { T a; };"),
    "zero array size": WRAP.format("struct S { uint8 a[0]; };"),
    "zero sequence bound": WRAP.format("struct S { sequence<int32, 0> a; };"),
    "zero string bound": WRAP.format("struct S { string<0> a; };"),
    "constant out of range": WRAP.format(
        "module S_Constants { const uint8 A = 256; }; struct S { int8 a; };"
    ),
    "negative unsigned constant": WRAP.format(
        "module S_Constants { const uint32 A = -1; }; struct S { int8 a; };"
    ),
    "constant string over its bound": WRAP.format(
        'module S_Constants { const string<2> A = "abc"; }; struct S { int8 a; };'
    ),
    "default out of range": WRAP.format("struct S { @default (value=300) uint8 a; };"),
    "default string over its bound": WRAP.format(
        'struct S { @default (value="abc") string<2> a; };'
    ),
    "array default of the wrong length": WRAP.format(
        'struct S { @default (value="(1, 2)") int32 a[3]; };'
    ),
    "sequence default over its bound": WRAP.format(
        'struct S { @default (value="(1, 2, 3)") sequence<int32, 2> a; };'
    ),
    "array default element out of range": WRAP.format(
        'struct S { @default (value="(1, -1)") uint8 a[2]; };'
    ),
}


@pytest.mark.parametrize("text", BAD.values(), ids=BAD.keys())
def test_malformed_idl_raises_idl_syntax_error(text: str) -> None:
    with pytest.raises(IdlSyntaxError) as err:
        parse_idl(text, "bad.idl")
    assert isinstance(err.value, WireError)
    assert err.value.path == "bad.idl"
    assert 1 <= err.value.line <= text.count("\n") + 1
    assert str(err.value).startswith(f"bad.idl:{err.value.line}: ")


def test_error_names_the_line() -> None:
    text = "module p { module msg {\n  struct S {\n    int8 a;\n    bogus b c;\n  };\n}; };"
    with pytest.raises(IdlSyntaxError) as err:
        parse_idl(text, "x.idl")
    assert err.value.line == 4
    assert "'c'" in err.value.detail


VALID = WRAP.format("""
  module S_Constants { const uint8 A = 1; const string B = "b"; };
  struct S {
    @default (value="(1, 2)") sequence<int32, 4> a;
    string<8> b;
    double c[2];
    p::msg::T d;
  };""")
TOKENS = [
    "module",
    "struct",
    "typedef",
    "const",
    "sequence",
    "<",
    ">",
    "[",
    "]",
    "{",
    "}",
    ";",
    "@default",
    "(",
    ")",
    "value=",
    "0",
    "-1",
    "1.5",
    '"x"',
    "'c'",
    "::",
    "string",
    "int32",
    "S_Constants",
    "@key",
    "0x",
    "=",
    ",",
    "TRUE",
    "/*",
    '"',
    "#define",
]


@settings(max_examples=300, deadline=None)
@given(
    edits=st.lists(
        st.tuples(st.integers(0, len(VALID)), st.integers(0, 8), st.sampled_from(TOKENS)),
        min_size=1,
        max_size=3,
    )
)
def test_mutated_idl_parses_or_raises_idl_syntax_error(edits: list[tuple[int, int, str]]) -> None:
    """Whatever the damage, the parser answers with a model or an IdlSyntaxError."""
    text = VALID
    for at, cut, token in edits:
        text = text[:at] + f" {token} " + text[at + cut :]
    with contextlib.suppress(IdlSyntaxError):
        parse_idl(text, "fuzz.idl")
