"""Issue 26 in a real headless Chromium against `rcan-rtps run --sim`: sign in, the robot on
the plot, approve and deny from the page, the e-stop (seen by an rclpy subscriber) and its
clear by an OWNER, values rendered inert, what a GUEST sees. Screenshots: .artifacts/console/.

Marked interop: under CI=true a skip (no chromium, no selenium, no oracle) is a failure.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from waiting import eventually_sync

from tests.console.browser import Page, Sim, chromium, run_sim

pytestmark = [pytest.mark.interop, pytest.mark.slow]

HOSTILE_MODEL = '<img src=x onerror="window.__pwned=1">planner-7b'
HOSTILE_THOUGHT = "<script>window.__pwned=2</script>"


@pytest.fixture
def sim(tmp_path: Path, domain_id: int) -> Iterator[Sim]:
    yield from run_sim(tmp_path, domain_id)


@pytest.fixture
def browser() -> Iterator[Any]:
    driver = chromium()
    try:
        yield driver
    finally:
        driver.quit()


def page_for(browser: Any, sim: Sim, name: str) -> Page:
    page = Page(browser, sim, name)
    page.open()
    return page


def held_move(sim: Sim, linear_x: float, **ai: Any) -> str:
    """A move with low confidence: the demo's confidence gate holds it for an owner."""
    code, body = sim.call(sim.user, "POST", "/api/command", {
        "action": "move", "params": {"linear_x": linear_x, "duration_s": 2.0},
        "ai_model": "planner-7b", "confidence": 0.3, **ai})
    assert (code, body["outcome"]) == (202, "pending_auth"), body
    return str(body["pending_id"])


def test_sign_in_and_the_simulated_robot_moves_on_the_plot(browser: Any, sim: Sim) -> None:
    page = page_for(browser, sim, "operator")
    assert page.visible("#sign-in-form") and not page.visible("#estop")
    page.sign_in("not-a-token-of-this-bridge")
    page.wait("return document.getElementById('sign-in-error').textContent === "
              "'token refused'", "the refusal shown")
    assert page.js("return sessionStorage.length") == 0

    page.sign_in(sim.user)
    page.signed_in_as("operator (USER)")
    assert page.js("return sessionStorage.getItem('rcan-rtps.token')") == sim.user
    assert page.js("return document.cookie") == ""
    assert page.visible("#estop")
    assert not page.visible("#approvals-card") and not page.visible("#audit-card")
    assert not page.visible("#clear-estop")
    polygon = page.js("return document.getElementById('workspace').getAttribute('points')")
    assert polygon == "-20,20 20,20 20,-20 -20,-20"  # the safety manifest's, y up

    page.wait("return document.getElementById('robot').getAttribute('visibility') === "
              "'visible'", "the robot on the plot")
    start = page.robot_x()
    assert start is not None
    code, body = sim.call(sim.user, "POST", "/api/command", {
        "action": "move", "params": {"linear_x": 0.5, "duration_s": 2.0}})
    assert code == 200, body
    eventually_sync(lambda: (page.robot_x() or 0.0) > start + 0.6, timeout=30,
                    what=lambda: f"the robot past x={start + 0.6} on the plot "
                                 f"(at {page.robot_x()})")
    trail = page.js("return document.getElementById('trail').getAttribute('points')")
    assert len(trail.split()) >= 10, trail  # driven, sample by sample
    page.wait("return document.querySelector('[data-fact=state]') !== null", "the facts")
    page.screenshot("moved")
    assert page.small_touch_targets() == []
    assert page.console_errors() == []

    # the token lives in this tab only: a sign-out forgets it
    page.sign_out()
    browser.refresh()
    page.wait("return document.readyState === 'complete' && "
              "!document.getElementById('sign-in').hidden", "the sign-in page after reload")


def test_an_owner_approves_one_held_command_and_denies_another(browser: Any, sim: Sim) -> None:
    page = page_for(browser, sim, "owner")
    page.sign_in(sim.owner)
    page.signed_in_as("owner (OWNER)")
    page.wait("return document.getElementById('approvals-count').textContent === '0'",
              "the empty approvals queue")
    assert page.visible("#audit-card")

    start = sim.status()["telemetry"]["position"]["x"]
    pending = held_move(sim, 0.5, thought_id=HOSTILE_THOUGHT)
    card = f"li[data-pending='{pending}']"
    page.wait("return document.querySelector(arguments[0]) !== null",
              "the held move, pushed to the page", card)
    assert "planner-7b" in page.text(card) and "0.30" in page.text(card)
    page.element(f"{card} input").send_keys("clear path, checked on camera")
    page.element(f"{card} button[data-verdict=approve]").click()
    page.wait("return document.querySelector(arguments[0]) === null",
              "the approved move gone from the queue", card)
    eventually_sync(lambda: sim.status()["telemetry"]["position"]["x"] > start + 0.5,
                    timeout=30, what="the approved move driving the robot")
    approved = [e for e in sim.entries() if e["event"] == "HITL_AUTHORIZED"]
    assert [(e["principal"], e["approvals"][-1]["reason"]) for e in approved] == [
        ("owner", "clear path, checked on camera")]

    # the view the README shows: a navigation goal under way, a command waiting
    code, body = sim.call(sim.user, "POST", "/api/command", {
        "action": "navigate", "params": {"x": 2.0, "y": 1.5, "yaw": 0.0}})
    assert code == 200, body
    waiting = held_move(sim, 0.4)
    page.wait("return document.querySelector(`li[data-goal] progress[value]`) !== null && "
              "document.querySelector(arguments[0]) !== null", "a goal's progress, a held move",
              f"li[data-pending='{waiting}']")
    page.screenshot("overview")
    sim.call(sim.owner, "POST", "/api/hitl/withdraw", {"pending_id": waiting})

    # a second one, with markup where an AI names its model: denied, and it never runs
    sim.call(sim.user, "POST", "/api/command", {"action": "stop"})
    eventually_sync(lambda: sim.status()["telemetry"]["velocity"]["linear_x"] == 0.0,
                    timeout=30, what="the robot at rest")
    pending = held_move(sim, 0.8, ai_model=HOSTILE_MODEL)
    card = f"li[data-pending='{pending}']"
    page.wait("return document.querySelector(arguments[0]) !== null", "the second one", card)
    assert HOSTILE_MODEL in page.text(card)  # shown as the text it is
    page.wait("return [...document.querySelectorAll('#audit td')].some("
              "td => td.textContent.includes(arguments[0]))", "the thought id in the audit tail",
              HOSTILE_THOUGHT)
    assert page.js("return document.querySelectorAll('#approvals img, #audit script').length") == 0
    assert page.js("return document.scripts.length") == 1  # app.js, nothing added
    assert page.js("return window.__pwned === undefined")
    page.screenshot("approvals")
    before = sim.status()["telemetry"]["position"]["x"]
    page.element(f"{card} input").send_keys("not now")
    page.element(f"{card} button[data-verdict=deny]").click()
    page.wait("return document.querySelector(arguments[0]) === null", "the denied one gone",
              card)

    def denials() -> list[tuple[str, str]]:
        return [(e["pending_id"], e["approvals"][-1]["reason"]) for e in sim.entries()
                if e["event"] == "HITL_DENIED"]
    # The card goes once the command is out of the store, its audit entry right after (a
    # denial moves nothing: no entry has to be durable before it).
    eventually_sync(lambda: denials() != [], timeout=30, what="the denial in the audit log")
    assert denials() == [(pending, "not now")]
    assert abs(sim.status()["telemetry"]["position"]["x"] - before) < 0.05

    page.wait("return document.getElementById('verify').dataset.state === 'ok'",
              "the chain verified")
    assert page.js("return window.__pwned === undefined")
    assert page.console_errors() == []


def test_estop_from_the_page_reaches_ros_and_only_an_owner_clears_it(
        browser: Any, sim: Sim, jazzy_python: Path) -> None:
    from oracle.client import RclpyOracle

    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    with RclpyOracle(jazzy_python, "estop_watch", domain_id=sim.domain_id, env=env) as oracle:
        oracle.call("subscribe", topic="/robot1/emergency_stop", type="std_msgs/msg/Bool",
                    qos="transient_local")
        assert oracle.call("wait_matched", topic="/robot1/emergency_stop", timeout=60) >= 1
        seen: list[Any] = []

        def received(value: bool) -> bool:
            seen.extend(oracle.call("take", topic="/robot1/emergency_stop"))
            return {"data": value} in seen

        held_move(sim, 0.2)  # waiting for an owner: a guest must not be offered it
        page = page_for(browser, sim, "guest")
        page.sign_in(sim.viewer)
        page.signed_in_as("viewer (GUEST)")
        page.wait("return document.querySelector('[data-fact=\"waiting for approval\"]')"
                  "?.textContent === '1'", "STATUS counting the held command")
        assert not page.visible("#approvals-card") and not page.visible("#audit-card")
        assert page.js("return document.querySelectorAll('[data-verdict]').length") == 0
        assert page.visible("#guest-note") and not page.visible("#clear-estop")

        page.element("#estop").click()  # one touch, no confirmation
        page.wait("return document.body.dataset.estop === 'latched' && "
                  "!document.getElementById('banner').hidden", "the page showing the e-stop")
        eventually_sync(lambda: received(True), timeout=30,
                        what=lambda: f"emergency_stop true on ROS (seen {seen})")
        page.wait("return document.querySelector('[data-fact=\"e-stop\"]')?.textContent"
                  " === 'LATCHED'", "STATUS showing the latch")
        assert not page.visible("#clear-estop")  # a guest may not clear it
        page.screenshot("estop")
        estops = [e for e in sim.entries() if e.get("action_type") == "estop"]
        assert [e["principal"] for e in estops] == ["viewer"]

        page.sign_out()
        page.sign_in(sim.owner)
        page.signed_in_as("owner (OWNER)")
        page.wait("return !document.getElementById('clear-estop').hidden",
                  "the owner's clear button")
        seen.clear()
        page.element("#clear-estop").click()
        page.wait("return document.body.dataset.estop === 'released' && "
                  "document.getElementById('banner').hidden", "the e-stop cleared on the page")
        eventually_sync(lambda: received(False), timeout=30,
                        what=lambda: f"emergency_stop false on ROS (seen {seen})")
        assert not sim.status()["estop"]
        assert page.console_errors() == []


def test_other_publishers_on_the_command_topics_are_shown_expected_or_not(
        browser: Any, tmp_path: Path, domain_id: int, jazzy_python: Path) -> None:
    """The demo's config declaring nav2's controller_server on cmd_vel: it and a teleop node
    (rclpy, publishing there too) are listed on the page by node and topic, one expected, the
    other not (and only the other is a fault)."""
    from oracle.client import RclpyOracle

    from rcan_rtps.bridge.demo import demo_yaml

    text = demo_yaml(state_dir=tmp_path / "state", port=8765, domain_id=domain_id,
                     namespace="/robot1")
    declared = "    foreign_publishers: {expected: {cmd_vel: [/robot1/controller_server]}}\n"
    config = tmp_path / "expecting.rcan.yaml"
    config.write_text(text.replace("    nav_frame_id: map\n", "    nav_frame_id: map\n" + declared))
    sims = run_sim(tmp_path, domain_id, "--config", str(config))
    sim = next(sims)
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    try:
        with RclpyOracle(jazzy_python, "controller_server", "/robot1", domain_id=domain_id,
                         env=env) as nav2, \
                RclpyOracle(jazzy_python, "teleop", "/robot1", domain_id=domain_id,
                            env=env) as teleop:
            page = page_for(browser, sim, "operator")
            page.sign_in(sim.user)
            page.signed_in_as("operator (USER)")
            page.wait("return document.querySelector('#foreign li.empty') !== null",
                      "no other publisher listed yet")
            for oracle in (nav2, teleop):
                oracle.call("publisher", topic="/robot1/cmd_vel",
                            type="geometry_msgs/msg/Twist")
            shown = ("return [...document.querySelectorAll('#foreign li[data-foreign]')].map("
                     "li => [li.dataset.expected, li.textContent])")
            # Unnamed until its ros_discovery_info comes, a node is not yet expected.
            page.wait(shown + ".filter(([expected, text]) => expected === 'true' || "
                      "text.startsWith('/robot1/teleop')).length === 2",
                      "both publishers on the page, named")
            rows = sorted(page.js(shown))
            assert [row[0] for row in rows] == ["false", "true"]
            (_, surprise), (_, design) = rows
            assert surprise.startswith("/robot1/teleop on /robot1/cmd_vel") and \
                surprise.endswith("not expected"), surprise
            assert design.startswith("/robot1/controller_server on /robot1/cmd_vel") and \
                design.endswith(" expected") and "not expected" not in design, design
            assert "geometry_msgs/msg/Twist, 1 writer(s)" in design
            faults = page.js("return [...document.querySelectorAll('#faults li')]"
                             ".map(li => li.textContent)")
            (warning,) = [f for f in faults if "foreign_publisher" in f]
            assert warning.startswith("WARN") and "/robot1/teleop" in warning
            assert "controller_server" not in warning
            page.screenshot("other-publishers")
            teleop.call("unpublish", topic="/robot1/cmd_vel")
            page.wait("return document.querySelectorAll('#foreign li[data-foreign]').length"
                      " === 1 && document.querySelector('#foreign li[data-expected=true]')"
                      " !== null", "the teleop node gone from the page")
            assert page.console_errors() == []
    finally:
        sims.close()


def test_an_owner_whose_approvals_must_be_signed_is_offered_deny_only(
        browser: Any, tmp_path: Path, domain_id: int) -> None:
    """The page cannot sign: under a `required` policy it says where to approve from, and
    denies (a denial needs no signature)."""
    import base64

    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from rcan_rtps.bridge.demo import OWNER_TOKEN_ENV, demo_yaml

    public = base64.b64encode(Ed25519PrivateKey.generate().public_key().public_bytes_raw())
    owner = f"{{name: owner, role: OWNER, token_env: {OWNER_TOKEN_ENV}}}"
    text = demo_yaml(state_dir=tmp_path / "state", port=8765, domain_id=domain_id,
                     namespace="/robot1")
    assert owner in text
    config = tmp_path / "signing-owner.rcan.yaml"
    config.write_text(text.replace(owner, owner[:-1] + (
        ", signatures: {policy: required, keys: [{kid: owner-ed, alg: ed25519, "
        f"public_key: {public.decode()}}}]}}}}")))
    sims = run_sim(tmp_path, domain_id, "--config", str(config))
    sim = next(sims)
    try:
        page = page_for(browser, sim, "owner-signing")
        page.sign_in(sim.owner)
        page.signed_in_as("owner (OWNER)")
        pending = held_move(sim, 0.5)
        card = f"li[data-pending='{pending}']"
        page.wait("return document.querySelector(arguments[0]) !== null", "the held move", card)
        assert page.js("return document.querySelector(arguments[0]) === null",
                       f"{card} button[data-verdict=approve]")
        assert "must be signed" in page.text(f"{card} .signed-only")
        page.element(f"{card} button[data-verdict=deny]").click()
        page.wait("return document.querySelector(arguments[0]) === null", "the denied one gone",
                  card)
        assert [e["pending_id"] for e in sim.entries() if e["event"] == "HITL_DENIED"] == [
            pending]
        assert page.console_errors() == []
    finally:
        next(sims, None)
