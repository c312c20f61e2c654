"""Motion priorities and locks from `bridge.motion` (twist_mux-like arbitration)."""

from __future__ import annotations

from rcan_rtps.config import MotionConfig
from rcan_rtps.rcan import Role

from .rbac import Principal


class MotionPriorities:
    """A principal's priority: its own (by name), else its role's, else the default."""

    def __init__(self, config: MotionConfig | None = None) -> None:
        config = config or MotionConfig()
        self._default = config.default_priority
        # Keyed by the profile's name: the config may use RCAN v2's (OPERATOR for USER).
        self._roles = {Role[role].name: p for role, p in config.role_priorities.items()}
        self._principals = dict(config.principal_priorities)
        self._locks = {lock.name: lock.priority for lock in config.locks}

    def of(self, principal: Principal) -> int:
        own = self._principals.get(principal.name)
        if own is not None:
            return own
        return self._roles.get(principal.role.name, self._default)

    def lock(self, name: str) -> int | None:
        """The configured priority of lock `name`; None if there is no such lock."""
        return self._locks.get(name)
