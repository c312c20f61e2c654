"""The bridge's exceptions: one base, so a caller embedding the bridge can catch them all."""


class BridgeError(Exception):
    """Base of every error the bridge itself raises."""


class BridgeStateError(BridgeError, RuntimeError):
    """A lifecycle call the bridge's state does not allow (start twice, start after stop)."""
