"""The operator console: a static page (HTML, CSS, JavaScript modules) the bridge serves at
`/console/`, shipped inside the wheel and never built at install time (no bundler, no CDN,
no framework: a robot's network is often offline).

This module only finds the files; `rcan_rtps.api._console_pages` serves them, with the headers that
keep the page to its own origin. What the page shows comes from `/api/*`, with the bearer
token the operator signs in with (kept in the tab's sessionStorage); see docs/console.md.
"""

from __future__ import annotations

import re
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    if sys.version_info >= (3, 11):
        from importlib.resources.abc import Traversable
    else:
        from importlib.abc import Traversable

__all__ = ["CONTENT_TYPES", "CSP", "asset", "asset_names"]

# Every asset the console has, by suffix; anything else in the folder is not served.
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".svg": "image/svg+xml",
}
_NAME = re.compile(r"^[a-z0-9][a-z0-9-]*\.(html|css|js|svg)$")

# Only the page's own files and API; nothing inline (no script, no style attribute or element,
# no eval), nothing framed, nothing posted elsewhere. `connect-src 'self'` covers the same
# origin's ws:/wss: too (CSP Level 3).
CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
       "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'none'; "
       "frame-ancestors 'none'")


def _folder() -> Traversable:
    # Imported here: importlib.resources (and the zip reader it loads) costs a run ~0.3 MB of
    # idle memory, and the console's files are only looked at when someone opens it.
    from importlib import resources

    return resources.files(__name__).joinpath("static")


def asset_names() -> frozenset[str]:
    """The files the console serves (names, flat: no folders)."""
    return frozenset(f.name for f in _folder().iterdir() if f.is_file() and _NAME.match(f.name))


def asset(name: str) -> bytes:
    """One asset's bytes (a name from `asset_names`)."""
    if name not in asset_names():
        raise KeyError(name)
    data: bytes = _folder().joinpath(name).read_bytes()
    return data
