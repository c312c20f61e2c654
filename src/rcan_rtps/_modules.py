"""Modules a run lets go of once it no longer needs them (issue 14 and 27: idle memory).

A module's code and data are freed once nothing refers to it: not `sys.modules`, not its
package's attribute, not a function or class of it kept anywhere. What is let go of before
the rest of a start has been built is reused by it (the holes left are filled), rather than
left free among live objects, which keeps the process's pages resident.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable

# Modules only a start runs: the audit log's replay (`Governor.from_config`), the IDL parser
# and the XTypes describer (a start makes the topics of everything a stop publishes; a service
# client loads what its endpoints nest when it is made, `TypeStore.load_nested`, and an action
# client's cancel service describes its topics ahead, `ServiceClient.describe_ahead`). A later
# user imports them again — a first goal or arm command, never a stop.
START_ONLY = ("rcan_rtps.governance.resume", "rcan_rtps.ros.typesys.idl_parser",
              "rcan_rtps.ros.typesys.xtypes")


def let_go(names: Iterable[str]) -> None:
    """Forgets the modules `names` (and their attribute on their package); a later user
    imports them again."""
    for name in names:
        if sys.modules.pop(name, None) is None:
            continue
        parent, _, attr = name.rpartition(".")
        if parent in sys.modules:
            vars(sys.modules[parent]).pop(attr, None)
