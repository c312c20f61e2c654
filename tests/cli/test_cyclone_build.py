"""doctor's look at the Cyclone C library: where security plugins are found, and the versions
read off the library the binding really loaded."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from rcan_rtps.cli import _cyclone_build as cyclone

pytestmark = pytest.mark.offline


def test_the_loaded_library_is_the_wheels_of_the_bindings_release() -> None:
    import importlib.metadata

    library = cyclone.c_library()
    assert library.path is not None and library.path.is_file()
    assert library.version == importlib.metadata.version("cyclonedds")
    assert library.origin == "bundled in the binding's wheel"
    assert cyclone.build_options(library)["DDS-Security"] is False  # PyPI's build


def test_a_plugin_in_a_directory_below_libddsc_is_found_but_not_on_the_path(
        tmp_path: Path) -> None:
    # Debian's layout: <multiarch>/libddsc.so.* and <multiarch>/libddsc0debian/libdds_security_*
    real = cyclone.c_library().path
    assert real is not None
    libddsc = tmp_path / "libddsc.so.11.0.1"
    shutil.copy(real, libddsc)
    (tmp_path / "libddsc0debian").mkdir()
    shutil.copy(real, tmp_path / "libddsc0debian" / "libdds_security_auth.so")  # a real ELF
    auth, access, crypto = (cyclone._plugin(role, name, libddsc)
                            for role, name in cyclone.SECURITY_PLUGINS)
    assert auth.found == tmp_path / "libddsc0debian" / "libdds_security_auth.so"
    assert auth.loadable and not auth.on_search_path
    assert access.found is None and not access.loadable
    assert crypto.found is None and not crypto.loadable
