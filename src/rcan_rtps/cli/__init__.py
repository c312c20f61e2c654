"""The `rcan-rtps` command line, shaped like ros2cli. No public Python API: run the command."""

import mimetypes

# aiohttp.web builds its static-file MIME table at import, and that first loads the system's
# /etc/mime.types into mimetypes' global table, kept for the process's life (~0.35 MB). The
# command line serves no files: marked loaded, aiohttp's table is Python's built-in one; a
# mimetypes.guess_type() call still loads the system's table on first use.
mimetypes.inited = True

__all__: list[str] = []
