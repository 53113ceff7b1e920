"""The operator screen in a real headless Chromium (Playwright with Debian's chromium), against
``comp-daemon run --sim`` as a process.

The page loads with a token from the link's fragment, goes live over server-sent events, shows the
loop's numbers changing without a reload (faster than its 5 s status poll could change them), the
joints, the queue with each compensated target's model uncertainty (σ), the fitted model with
Table 2, and logs no console error. A screenshot is saved
in the test's folder, and also at ``$DASHBOARD_SCREENSHOT`` when set (the repository's
``docs/screenshots/dashboard.png`` is made by tests/test_screenshots.py).

Without ``/usr/bin/chromium`` the test is skipped, except in CI (``CI=true``), where ``.ci/run``
installs it and its absence is a failure. The browser is never downloaded.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from e2e_daemon import TOKENS, DaemonProcess, fit_and_activate, sample_campaign, upload_campaign, wait_until

from comp_daemon.sim.scenario import load_scenario

pytestmark = pytest.mark.slow

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def _need_chromium() -> None:
    if CHROMIUM.is_file():
        return
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{CHROMIUM} is missing in CI (.ci/run installs Debian's chromium)")
    pytest.skip(f"{CHROMIUM} is not installed (apt-get install chromium); the dashboard test needs it")


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[DaemonProcess]:
    _need_chromium()
    d = DaemonProcess(tmp_path)
    try:
        yield d
    finally:
        d.cleanup()


def number(text: str) -> float:
    return float(text.strip().replace(",", ""))


def test_dashboard_goes_live_in_chromium(daemon: DaemonProcess, tmp_path: Path) -> None:
    from playwright.sync_api import expect, sync_playwright

    campaign = sample_campaign(tmp_path / "campaign.csv", n=60, seed=4)
    daemon.start("--calibrate-gratings")
    daemon.wait_http()
    daemon.wait_ready(60, allow=["no model is active"])
    with daemon.client("engineer") as eng:
        fit_and_activate(eng, upload_campaign(eng, campaign, "cell-campaign-2026-11")["id"], "kinematic")
    daemon.wait_ready(10)

    console_errors: list[str] = []
    urls: list[str] = []
    token = TOKENS["operator"]
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.on("console", lambda m: console_errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: console_errors.append(f"page error: {e}"))
            page.on("request", lambda req: urls.append(req.url))
            page.goto(f"{daemon.base_url}/dashboard/#token={token}")

            expect(page.locator("#live-text")).to_have_text("live", timeout=15_000)
            expect(page.locator("#who")).to_have_text("mes · operator")
            expect(page.locator("#ready-text")).to_have_text("ready", timeout=10_000)
            expect(page.locator("#models tbody tr")).to_have_count(1, timeout=10_000)
            expect(page.locator("#joints tbody tr")).to_have_count(6, timeout=10_000)
            expect(page.locator("#lat-p50")).not_to_have_text("—", timeout=10_000)
            assert number(page.locator("#lat-p50").inner_text()) >= 0.0

            # live numbers: the cycle count read eight times in 2 s changes at least three times;
            # the page polls /api/status only every 5 s, so the changes came over the event stream
            readings = []
            for _ in range(9):
                readings.append(int(number(page.locator("#cycles").inner_text())))
                page.wait_for_timeout(250)
            assert readings == sorted(readings), readings
            assert len(set(readings)) >= 4, readings

            # the MES posts a batch; the queue and the joints follow it live
            home = [float(v) for v in load_scenario("kr210-cell").campaign.home_deg]
            targets: list[dict[str, Any]] = [
                {
                    "pose_id": f"rib-{k + 1:02d}",
                    **{
                        f"a{i + 1}": round(v + (3.0 * k - 9.0 if i < 3 else 0.0), 3)
                        for i, v in enumerate(home)
                    },
                }
                for k in range(8)
            ]
            with daemon.client("operator") as mes:
                r = mes.post(
                    "/api/batches", json={"targets": targets}, headers={"Idempotency-Key": "screen-1"}
                )
                assert r.status_code == 201, r.text
                ids = [t["id"] for t in r.json()["targets"]]

                def some_done_one_running() -> bool:
                    states = [mes.get(f"/api/targets/{i}").json()["state"] for i in ids]
                    return states.count("done") >= 3 and any(s in ("moving", "settling") for s in states)

                wait_until(some_done_one_running, 60, "three targets done and one under way", every_s=0.1)
                done = [t for t in (mes.get(f"/api/targets/{i}").json() for i in ids) if t["state"] == "done"]
            # each compensated target shows the kinematic model's 1-σ uncertainty at its commanded axes
            assert done and all(0.0 < t["predicted_sigma_mm"] < 1.0 for t in done), done
            page.locator("#show-finished").check()
            for t in done:
                row = page.locator("#targets tbody tr", has_text=t["request"]["pose_id"])
                expect(row.locator("td.sigma")).to_have_text(f"{t['predicted_sigma_mm']:.4f}", timeout=10_000)
            expect(page.locator("#current-target")).not_to_have_text("no target", timeout=10_000)
            expect(page.locator("#targets tbody tr").first).to_be_visible()
            expect(page.locator("#table2 tbody tr").first).to_be_visible()
            joints_before = page.locator("#joints tbody").inner_text()
            page.wait_for_timeout(600)
            assert page.locator("#joints tbody").inner_text() != joints_before  # readings and errors

            time.sleep(0.3)
            shot = tmp_path / "dashboard.png"
            page.screenshot(path=str(shot), full_page=True)
            assert shot.stat().st_size > 20_000
            wanted = os.environ.get("DASHBOARD_SCREENSHOT")
            if wanted:
                shutil.copyfile(shot, wanted)

            assert console_errors == [], console_errors
            assert not any(token in u for u in urls), "the token must never travel in a URL"
            assert any(u.endswith("/api/events") for u in urls)

            # stopping the daemon ends the stream cleanly; the page says so instead of freezing
            assert daemon.sigterm() == 0, daemon.tail()
            expect(page.locator("#live-text")).to_have_text("reconnecting", timeout=10_000)
        finally:
            browser.close()
