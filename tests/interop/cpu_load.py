"""A CPU load generator for tests that must hold on a busy robot computer: one busy-looping
process per core, at the tests' own priority, for as long as the context lasts."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

_BURN = "import itertools\nfor _ in itertools.count(): pass\n"


@contextmanager
def burning_cpus() -> Iterator[int]:
    """Every core kept busy meanwhile; yields how many burner processes run."""
    burners = [subprocess.Popen([sys.executable, "-c", _BURN])
               for _ in range(os.cpu_count() or 2)]
    try:
        yield len(burners)
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()
