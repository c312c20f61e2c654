"""What `rcan-rtps` and `python -m rcan_rtps` start: the command line, loaded under a guard.

Loading the command line (argparse, logging, msgspec) takes a while on a busy machine, and a
Ctrl-C landing then came out as a traceback: `cli.main` catches it only once it has loaded.
This module imports nothing of its own, so the unguarded moment is the interpreter's start.
"""

from __future__ import annotations

import sys

EXIT_INTERRUPTED = 130


def main() -> int:
    try:
        from .cli.main import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("rcan-rtps: interrupted\n")
        return EXIT_INTERRUPTED
    return cli_main()
