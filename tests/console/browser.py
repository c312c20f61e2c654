"""A real headless Chromium (Debian's `chromium` and `chromium-driver`, installed by
scripts/test.sh) driven by Selenium, and `rcan-rtps run --sim` for it to look at.

Nothing here downloads a browser or a driver: the driver is `/usr/bin/chromedriver`, given to
Selenium as its Service (so selenium-manager is never asked), and the browser is
`/usr/bin/chromium`. Run the tests inside the private network namespace (scripts/netns, as
scripts/test.sh does): the browser then cannot reach anything but loopback either.

Screenshots go to `.artifacts/console/` (or `$RCAN_RTPS_ARTIFACTS/console/`); each test prints
where.
"""

from __future__ import annotations

import json
import os
import tempfile
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.error import HTTPError

import pytest
from waiting import eventually_sync

from tests.interop.run_process import RunProcess, child_env

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = Path(os.environ.get("RCAN_RTPS_CHROMIUM", "/usr/bin/chromium"))
CHROMEDRIVER = Path(os.environ.get("RCAN_RTPS_CHROMEDRIVER", "/usr/bin/chromedriver"))
ARTIFACTS = Path(os.environ.get("RCAN_RTPS_ARTIFACTS", ROOT / ".artifacts")) / "console"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--window-size=1280,1000")
DESKTOP = {"width": 1280, "height": 1000, "deviceScaleFactor": 1, "mobile": False}
PHONE = {"width": 390, "height": 844, "deviceScaleFactor": 2, "mobile": True}
WAIT_S = 30.0  # generous: the machine is shared; nothing here measures speed


@dataclass
class Sim:
    url: str
    user: str
    owner: str
    viewer: str
    audit: Path
    domain_id: int
    process: RunProcess

    def call(self, token: str, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data, method=method, headers={
            "Authorization": f"Bearer {token}", "Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                return response.status, json.load(response)
        except HTTPError as refused:
            return refused.code, json.load(refused)

    def status(self) -> dict[str, Any]:
        code, body = self.call(self.user, "GET", "/api/status")
        assert code == 200, body
        return dict(body)

    def entries(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in self.audit.read_text().splitlines()]


def run_sim(tmp_path: Path, domain_id: int, *extra: str) -> Iterator[Sim]:
    """`run --sim`; `extra` arguments (a `--config`: the port it names is overridden) after
    the others."""
    process = RunProcess(["run", "--sim", "--port", "0", "--no-mdns", "--state-dir",
                          str(tmp_path / "state"), *extra], child_env(domain_id), demo=True)
    try:
        viewer = process.wait_for(r"GUEST \(viewer\)\s+(\S+)", 10).group(1)
        audit = Path(process.wait_for(r"audit log: (\S+)", 10).group(1))
        sim = Sim(process.url, process.user, process.owner, viewer, audit, domain_id, process)
        eventually_sync(lambda: sim.status()["ros"]["connected"], timeout=60,
                        what="the simulated robot's telemetry")
        yield sim
    finally:
        code = process.stop()
        assert code == 0, process.output()


def chromium() -> Any:
    """A fresh headless Chromium (its own profile: nothing stored carries over)."""
    pytest.importorskip("selenium", reason="the `test` extra installs selenium")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    for needed in (CHROMIUM, CHROMEDRIVER):
        if not needed.exists():
            pytest.skip(f"{needed} is missing: scripts/test.sh installs Debian's chromium "
                        "and chromium-driver")
    os.environ.setdefault("SE_OFFLINE", "true")  # selenium-manager, were it asked: no fetch
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    profile = tempfile.mkdtemp(prefix="rcan-console-chromium-")
    for flag in (*FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


class Page:
    """The console in one browser, as an operator uses it."""

    def __init__(self, driver: Any, sim: Sim, name: str) -> None:
        self.driver = driver
        self.sim = sim
        self.name = name

    def js(self, script: str, *args: Any) -> Any:
        return self.driver.execute_script(script, *args)

    def wait(self, script: str, what: str, *args: Any, timeout: float = WAIT_S) -> Any:
        return eventually_sync(lambda: self.js(script, *args), timeout=timeout, what=what)

    def element(self, css: str) -> Any:
        from selenium.webdriver.common.by import By

        return self.driver.find_element(By.CSS_SELECTOR, css)

    def visible(self, css: str) -> bool:
        return bool(self.js("const e = document.querySelector(arguments[0]);"
                            "return !!e && e.getClientRects().length > 0;", css))

    def text(self, css: str) -> str:
        return str(self.js("const e = document.querySelector(arguments[0]);"
                           "return e ? e.textContent : null;", css))

    def open(self) -> None:
        self.driver.get(self.sim.url + "/")
        self.wait("return location.pathname === '/console/' && "
                  "document.getElementById('sign-in-form') !== null && "
                  "document.readyState === 'complete'", "the console's sign-in page")

    def sign_in(self, token: str) -> None:
        field = self.element("#token")
        field.clear()
        field.send_keys(token)
        self.element("#sign-in-button").click()

    def signed_in_as(self, badge: str) -> None:
        self.wait("return document.getElementById('principal').textContent === arguments[0]"
                  " && document.getElementById('link').textContent === 'live'",
                  f"signed in as {badge}, live", badge)

    def sign_out(self) -> None:
        self.element("#sign-out").click()
        self.wait("return !document.getElementById('sign-in').hidden && "
                  "sessionStorage.length === 0", "the sign-in page again")

    def robot_x(self) -> float | None:
        x = self.js("return document.getElementById('robot').getAttribute('data-x')")
        return None if x is None else float(x)

    def screenshot(self, label: str) -> list[Path]:
        """Desktop and phone widths, from the top of the page; returns the files."""
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        self.js("window.scrollTo(0, 0)")
        saved = []
        for size, metrics in (("desktop", DESKTOP), ("phone", PHONE)):
            self.driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
            self.js("return new Promise(r => requestAnimationFrame(() => r(true)))")
            path = ARTIFACTS / f"{self.name}-{label}-{size}.png"
            self.driver.save_screenshot(str(path))
            saved.append(path)
        self.driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})
        print(f"console screenshots: {', '.join(str(p) for p in saved)}")
        return saved

    def small_touch_targets(self) -> list[str]:
        """Visible controls under 44×44 CSS px at phone width."""
        self.driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", PHONE)
        try:
            return list(self.js("""
              const small = [];
              for (const e of document.querySelectorAll('button, input, select')) {
                const r = e.getBoundingClientRect();
                if (r.width === 0 && r.height === 0) continue;  // not shown
                if (r.width < 44 || r.height < 44) small.push(
                  (e.id || e.textContent || e.tagName) + ' ' + r.width + 'x' + r.height);
              }
              return small;"""))
        finally:
            self.driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})

    def console_errors(self) -> list[str]:
        """What the page logged as errors (a CSP violation, an uncaught exception); an HTTP
        error status the page asked for (a refused token's 401) is not one."""
        return [e["message"] for e in self.driver.get_log("browser")
                if e["level"] == "SEVERE" and "Failed to load resource" not in e["message"]]
