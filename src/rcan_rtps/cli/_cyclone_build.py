"""What `rcan-rtps doctor` can learn of the Cyclone DDS under the Python binding: the C
library the binding loaded (where from, its version), the options it was built with, and
whether DDS-Security (what SROS2 needs) can run on it. Read off the library itself; nothing
here opens a participant."""

from __future__ import annotations

import ctypes
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from ..ros.security.settings import cyclone_has_security

# Cyclone's three security plugins, by the names its configuration loads them under
# (`dds.sec.auth.library.path` and friends default to these).
SECURITY_PLUGINS = (("authentication", "dds_security_auth"),
                    ("access control", "dds_security_ac"),
                    ("cryptography", "dds_security_crypto"))
_VERSION = re.compile(r"(\d+\.\d+\.\d+)")


@dataclass(frozen=True)
class CLibrary:
    path: Path | None  # None: the binding did not load one (CYCLONEDDS_PYTHON_NO_IMPORT_LIBS)
    version: str
    origin: str
    handle: ctypes.CDLL | None


@dataclass(frozen=True)
class Plugin:
    role: str
    name: str
    found: Path | None  # the file, where found beside libddsc
    loadable: bool
    on_search_path: bool  # loads by its bare name, as Cyclone's dlopen asks for it


def c_library() -> CLibrary:
    """The libddsc the binding loads, by the binding's own loader (wheel, CYCLONEDDS_HOME,
    the system path)."""
    from cyclonedds import internal

    handle = internal.load_cyclonedds()
    if handle is None or not handle._name:
        return CLibrary(None, "unknown", "not loaded (CYCLONEDDS_PYTHON_NO_IMPORT_LIBS)", None)
    path = Path(os.path.realpath(handle._name))
    match = _VERSION.search(path.name)
    return CLibrary(path, match.group(1) if match else "unknown", _origin(path), handle)


def _origin(path: Path) -> str:
    home = os.environ.get("CYCLONEDDS_HOME", "").strip()
    if path.parent.name.endswith(".libs") or path.parent.name == ".dylibs":
        return "bundled in the binding's wheel"
    if home and path.is_relative_to(Path(os.path.realpath(home))):
        return f"CYCLONEDDS_HOME={home}"
    return "the system library path"


def build_options(library: CLibrary) -> dict[str, bool]:
    """Options of the C build: the binding was compiled against its features.h, and the
    library's exports show whether security is built in."""
    from cyclonedds import _clayer

    options = {"type library": bool(getattr(_clayer, "HAS_TYPELIB", False)),
               "type discovery": bool(getattr(_clayer, "HAS_TYPE_DISCOVERY", False)),
               "topic discovery": bool(getattr(_clayer, "HAS_TOPIC_DISCOVERY", False))}
    # the same test the participant makes before it asks Cyclone for security
    options["DDS-Security"] = (library.handle is not None
                               and cyclone_has_security(library.handle))
    return options


def security_plugins(library: CLibrary) -> list[Plugin]:
    return [_plugin(role, name, library.path) for role, name in SECURITY_PLUGINS]


def _plugin(role: str, name: str, libddsc: Path | None) -> Plugin:
    file_name = _shared_library_name(name)
    on_path = _loads(file_name)
    found = _beside(file_name, libddsc) if libddsc else None
    loadable = on_path or (found is not None and _loads(str(found)))
    return Plugin(role, name, found, loadable, on_path)


def _shared_library_name(name: str) -> str:
    if sys.platform == "darwin":
        return f"lib{name}.dylib"
    if sys.platform == "win32":
        return f"{name}.dll"
    return f"lib{name}.so"


def _beside(file_name: str, libddsc: Path) -> Path | None:
    """The plugin in libddsc's directory or one below it (Debian keeps them in
    <multiarch>/libddsc0debian/, off the default library path)."""
    directory = libddsc.parent
    candidates = [directory / file_name, *sorted(directory.glob(f"*/{file_name}"))]
    return next((c for c in candidates if c.is_file()), None)


def _loads(name: str) -> bool:
    try:
        ctypes.CDLL(name)
    except OSError:
        return False
    return True
