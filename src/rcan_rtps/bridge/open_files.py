"""The process's limit on open files, raised toward its hard limit as a run starts.

Every connection is a file descriptor. With the common soft limit of 1024, a few clients
holding connections open (WebSockets, kept-alive requests; each principal's sockets are
bounded, `api._ws`, but principals are many) would leave none for the next — and the next may
be an e-stop. The hard limit is what the administrator allows; the soft one is only a default.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

WANTED = 65536  # plenty for a robot's clients; not "unlimited" (macOS refuses that)


def raise_open_file_limit(wanted: int = WANTED) -> int | None:
    """Raises the soft RLIMIT_NOFILE to min(hard, `wanted`) when it is lower; the soft limit
    now (None where there is no such limit: not Unix)."""
    try:
        import resource
    except ImportError:  # Windows: no rlimits
        return None
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(hard, wanted)
    if soft == resource.RLIM_INFINITY or soft >= target:
        return soft
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (ValueError, OSError) as exc:  # (macOS: above kern.maxfilesperproc)
        log.info("open files: the soft limit stays %d (raising it to %d failed: %s)", soft,
                 target, exc)
        return soft
    return target
