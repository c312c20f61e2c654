"""`notify.FanOutNotifier`: each PENDING_AUTH channel on its own, so one that fails (a
webhook down, the node closing) never silences the others (bridge spec §3.1 flow 3)."""

from __future__ import annotations

import pytest

from rcan_rtps.bridge.notify import FanOutNotifier
from rcan_rtps.rcan import PendingAuth

MESSAGE = PendingAuth(pending_id="p-1", original_command={"action": "arm_joint"},
                      confidence=None, ai_model=None, requires_auth_from_role="OWNER",
                      expires_at_ms=1, issued_by="planner")


class Failing:
    async def notify(self, message: PendingAuth) -> None:
        raise OSError("webhook down")


class Recording:
    def __init__(self) -> None:
        self.heard: list[PendingAuth] = []

    async def notify(self, message: PendingAuth) -> None:
        self.heard.append(message)


async def test_a_failing_channel_never_silences_the_others(
        caplog: pytest.LogCaptureFixture) -> None:
    before, after = Recording(), Recording()
    await FanOutNotifier([before, Failing(), after]).notify(MESSAGE)  # raises nothing
    assert before.heard == [MESSAGE] and after.heard == [MESSAGE]
    assert "via Failing failed: webhook down" in caplog.text
