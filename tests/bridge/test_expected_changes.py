"""A participant that was expected on a command topic and no longer is (a writer of another
node, or of an unnamed one, joined it there) is news: logged at WARNING and audited, like an
appearance. A real node's CommanderWatch, told the graph's publishers as the graph would."""

from __future__ import annotations

import logging
from typing import Any

import pytest
from test_expected_publishers import CMD_VEL, EXPECTED, writer

from rcan_rtps.bridge.commanders import CommanderWatch, foreign_publishers
from rcan_rtps.ros.participant import RosNode


@pytest.mark.parametrize("joining", ["/teleop", None])
async def test_an_expected_participant_that_is_no_longer_expected_is_reported(
        domain_id: int, caplog: pytest.LogCaptureFixture, joining: str | None) -> None:
    audited: list[tuple[dict[str, Any], bool]] = []
    with RosNode("commanders_change", "/robot1", domain_id=domain_id) as node:
        own = node.participant.guid.bytes
        watch = CommanderWatch(node, {CMD_VEL: True}, show=lambda found, motion: None,
                               audit=lambda facts, gone: audited.append((facts, gone)),
                               expected=EXPECTED)
        controller = writer(CMD_VEL, 1, "/controller_server")
        watch.update(foreign_publishers([controller], own, EXPECTED))
        watch.tick()
        assert [(f["node"], f["expected"], gone) for f, gone in audited] == [
            ("/controller_server", True, False)]
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="rcan_rtps.bridge.commanders"):
            watch.update(foreign_publishers([controller, writer(CMD_VEL, 1, joining, 1)],
                                             own, EXPECTED))
            watch.tick()
        assert [(f["expected"], f["writers"], gone) for f, gone in audited[1:]] == [
            (False, 2, False)]
        assert [r.levelno for r in caplog.records] == [logging.WARNING]
        # Back to its expected writer only: told (at INFO) and audited as expected again.
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="rcan_rtps.bridge.commanders"):
            watch.update(foreign_publishers([controller], own, EXPECTED))
            watch.tick()
        assert [(f["expected"], gone) for f, gone in audited[2:]] == [(True, False)]
        assert [r.levelno for r in caplog.records] == [logging.INFO]
