"""Name expansion against rcl itself (rclpy Jazzy's expand_topic_name), name by name."""

from __future__ import annotations

import itertools
import json
import subprocess
from pathlib import Path

from rcan_rtps.ros.errors import InvalidNameError
from rcan_rtps.ros.names import expand_topic_name

NAMESPACES = ("/ns", "/")
# Every name of up to four characters over these, and some substitutions.
NAMES = ["".join(p) for n in range(1, 5) for p in itertools.product("~/a1_", repeat=n)]
NAMES += ["{node}", "~/{node}", "a/{node}", "~{node}", "{node}x", "x{node}", "{ns}/x"]
# Ours on purpose: rcl makes `//x` of `{ns}/x` in the root namespace and then rejects it;
# we collapse the separator (names.py).
OURS = {("/", "{ns}/x")}

RCL = """
import json, sys
from rclpy.expand_topic_name import expand_topic_name
from rclpy.validate_full_topic_name import validate_full_topic_name
out = []
for ns, name in json.load(sys.stdin):
    try:
        full = expand_topic_name(name, "n", ns)
        validate_full_topic_name(full)
    except Exception:
        full = None
    out.append(full)
print(json.dumps(out))
"""


def ours(name: str, ns: str) -> str | None:
    try:
        return expand_topic_name(name, "n", ns)
    except InvalidNameError:
        return None


def test_we_resolve_exactly_the_names_rcl_resolves(jazzy_python: Path) -> None:
    cases = [(ns, name) for ns in NAMESPACES for name in NAMES if (ns, name) not in OURS]
    done = subprocess.run([str(jazzy_python), "-c", RCL], input=json.dumps(cases),
                          capture_output=True, text=True, timeout=120, check=True)
    rcl = json.loads(done.stdout)
    differ = [(ns, name, want, ours(name, ns)) for (ns, name), want in zip(cases, rcl, strict=True)
              if ours(name, ns) != want]
    assert not differ, differ
