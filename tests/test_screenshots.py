"""Screenshots of what engineers look at, in a real headless Chromium (Playwright with Debian's
chromium, launched as the dashboard test launches it): the dashboard of a running
``comp-daemon run --sim`` with a fitted model and targets done, the diagnosis report of a campaign
with two withheld effects, and the trial report of the stored full trial (``docs/trial-result.json``).

Each page must render: its headings are there, every report figure is drawn, it fetches nothing
from the network and logs no console error. The PNGs go to the test's folder, or to the folder
named by ``$COMP_DAEMON_SCREENSHOTS`` (the repository keeps them in ``docs/screenshots/``:
``COMP_DAEMON_SCREENSHOTS=docs/screenshots python -m pytest tests/test_screenshots.py``).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from diagnosis_campaigns import NOISE_FLOOR_MM, make_campaign
from e2e_daemon import TOKENS, DaemonProcess, fit_and_activate, sample_campaign, upload_campaign, wait_until
from test_e2e_dashboard import CHROMIUM, CHROMIUM_ARGS, _need_chromium

from comp_daemon.diagnosis import diagnose
from comp_daemon.diagnosis.report import render_report_html
from comp_daemon.sim.scenario import load_scenario
from comp_daemon.trial.report import render_html
from comp_daemon.trial.result import TrialResult

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
WIDTH = 1280


@pytest.fixture
def out_dir(tmp_path: Path) -> Path:
    wanted = os.environ.get("COMP_DAEMON_SCREENSHOTS")
    out = Path(wanted) if wanted else tmp_path / "screenshots"
    out.mkdir(parents=True, exist_ok=True)
    return out


@pytest.fixture
def browser() -> Iterator[Any]:
    _need_chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


class Watched:
    """A page whose console errors and requests are recorded."""

    def __init__(self, browser: Any, height: int, headers: dict[str, str] | None = None) -> None:
        self.errors: list[str] = []
        self.urls: list[str] = []
        self.page = browser.new_page(viewport={"width": WIDTH, "height": height}, extra_http_headers=headers)
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(f"page error: {e}"))
        self.page.on("request", lambda req: self.urls.append(req.url))

    def shot(self, path: Path, *, full_page: bool) -> None:
        self.page.screenshot(path=str(path), full_page=full_page)
        assert path.stat().st_size > 20_000, f"{path} is nearly empty"
        assert self.errors == [], self.errors
        _compact(path)


def _compact(path: Path) -> None:
    """Rewrite the PNG with a 256-colour palette (a third of the size; pages are flat colours)."""
    from PIL import Image

    with Image.open(path) as im:
        rgb = im.convert("RGB")
    found = rgb.getcolors(maxcolors=1 << 16)
    colours = 1 << 16 if found is None else len(found)  # None: more than that
    rgb.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
        path, optimize=True
    )
    assert colours > 8, f"{path} is nearly blank ({colours} colours)"


def _report_shot(browser: Any, html_path: Path, png: Path, h1: str, h2: list[str], n_figures: int) -> None:
    w = Watched(browser, 1000)
    w.page.goto(html_path.as_uri())
    assert h1 in w.page.locator("h1").inner_text()
    headings = w.page.locator("h2").all_inner_texts()
    assert all(h in headings for h in h2), headings
    figures = w.page.locator("figure.plot")
    assert figures.count() == n_figures
    for k in range(n_figures):
        box = figures.nth(k).locator("svg").bounding_box()
        assert box is not None and box["width"] > 300 and box["height"] > 150, (k, box)
    assert all(u.startswith("file://") for u in w.urls), w.urls
    w.shot(png, full_page=True)


def test_diagnosis_report_screenshot(browser: Any, out_dir: Path, tmp_path: Path) -> None:
    camp = make_campaign(
        "kr210", 71, [("backlash", 2, 8 * NOISE_FLOOR_MM), ("thermal", None, 5 * NOISE_FLOOR_MM)], n_poses=160
    )
    page = render_report_html(diagnose(camp.dataset, camp.robot))
    html_path = tmp_path / "diagnosis-report.html"
    html_path.write_text(page, encoding="utf-8")
    n_figures = len(re.findall(r"<figure class=plot ", page))
    assert n_figures >= 9
    _report_shot(
        browser,
        html_path,
        out_dir / "diagnosis-report.png",
        "Sim-to-real gap diagnosis",
        ["The ladder", "Before and after (check rows)", "The remaining error"],
        n_figures,
    )


def test_trial_report_screenshot(browser: Any, out_dir: Path, tmp_path: Path) -> None:
    page = render_html(TrialResult.load(ROOT / "docs" / "trial-result.json"))
    html_path = tmp_path / "trial-report.html"
    html_path.write_text(page, encoding="utf-8")
    _report_shot(
        browser,
        html_path,
        out_dir / "trial-report.png",
        "Seed 000's experiment",
        ["Table 2: positioning error of the target points", "Per target point (seed 000 Figs 7–10)"],
        7,
    )


def test_dashboard_screenshot(browser: Any, out_dir: Path, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    daemon = DaemonProcess(tmp_path)
    try:
        campaign = sample_campaign(tmp_path / "campaign.csv", n=120, seed=4)
        daemon.start("--calibrate-gratings")
        daemon.wait_http()
        daemon.wait_ready(60, allow=["no model is active"])
        with daemon.client("engineer") as eng:
            dataset_id = upload_campaign(eng, campaign, "cell-campaign-2026-11")["id"]
            fit_and_activate(eng, dataset_id, "kinematic")
            r = eng.post("/api/diagnoses", json={"dataset_id": dataset_id})
            assert r.status_code == 202, r.text
            diagnosis_id = r.json()["id"]
            job = wait_until(
                lambda: (
                    (j := eng.get(f"/api/jobs/{diagnosis_id}").json())["state"] in ("done", "failed") and j
                ),
                300,  # 20 s alone; minutes on a machine shared by many test runs
                "the diagnosis job",
                every_s=0.2,
            )
            assert job["state"] == "done", f"{job}"
        daemon.wait_ready(10)

        # the report as the daemon serves it, under its content security policy
        served = Watched(browser, 1000, headers={"Authorization": f"Bearer {TOKENS['viewer']}"})
        served.page.goto(f"{daemon.base_url}/api/diagnoses/{diagnosis_id}/report.html")
        assert "Sim-to-real gap diagnosis" in served.page.locator("h1").inner_text()
        assert served.page.locator("figure.plot svg").count() >= 9
        assert served.errors == [], served.errors
        served.page.close()

        w = Watched(browser, 1000)
        w.page.goto(f"{daemon.base_url}/dashboard/#token={TOKENS['engineer']}")
        expect(w.page.locator("#live-text")).to_have_text("live", timeout=15_000)
        expect(w.page.locator("#ready-text")).to_have_text("ready", timeout=10_000)
        assert "comp-daemon" in w.page.locator("h1").inner_text()
        assert w.page.locator("h2").count() >= 5

        home = [float(v) for v in load_scenario("kr210-cell").campaign.home_deg]
        targets = [
            {
                "pose_id": f"rib-{k + 1:02d}",
                **{f"a{i + 1}": round(v + (3.0 * k - 9.0 if i < 3 else 0.0), 3) for i, v in enumerate(home)},
            }
            for k in range(8)
        ]
        with daemon.client("operator") as mes:
            r = mes.post("/api/batches", json={"targets": targets}, headers={"Idempotency-Key": "shot-1"})
            assert r.status_code == 201, r.text
            ids = [t["id"] for t in r.json()["targets"]]

            def some_done() -> bool:
                states = [mes.get(f"/api/targets/{i}").json()["state"] for i in ids]
                return states.count("done") >= 3

            wait_until(some_done, 60, "three targets done", every_s=0.1)
        w.page.locator("#show-finished").check()
        expect(w.page.locator("#targets tbody tr").first).to_be_visible(timeout=10_000)
        expect(w.page.locator("#table2 tbody tr").first).to_be_visible(timeout=10_000)
        expect(w.page.locator("#joints tbody tr")).to_have_count(6, timeout=10_000)
        expect(w.page.locator("#diagnoses tbody tr").first).to_be_visible(timeout=10_000)
        # a finished diagnosis says so (not its last progress message); its ladder names each step's joints
        job_row = w.page.locator("#jobs tbody tr", has_text="diagnosis")
        expect(job_row).to_contain_text("report ready", timeout=10_000)
        w.page.locator("#diagnoses tbody tr").first.click()
        expect(w.page.locator("#ladder tbody tr").nth(1)).to_be_visible(timeout=10_000)
        labels = w.page.locator("#ladder tbody tr td:first-child").all_inner_texts()
        assert len(set(labels)) == len(labels), labels
        # the cell actions, with a target file refused by row and column
        rows = [home, [500.0 if i == 2 else v for i, v in enumerate(home)]]
        broken = "pose_id,a1,a2,a3,a4,a5,a6\n" + "".join(
            f"rib-{9 + k:02d}," + ",".join(f"{v:g}" for v in row) + "\n" for k, row in enumerate(rows)
        )
        transfer = w.page.evaluate_handle(
            "([t]) => { const dt = new DataTransfer();"
            " dt.items.add(new File([t], 'rib-9.csv', { type: 'text/csv' })); return dt; }",
            [broken],
        )
        w.page.locator("#drop").dispatch_event("drop", {"dataTransfer": transfer})
        expect(w.page.locator("[data-testid=refusal]")).to_contain_text("row 3, column a3", timeout=10_000)
        # the browser logs the refused request itself; the page shows the refusal
        w.errors[:] = [e for e in w.errors if "status of 422" not in e]
        w.page.evaluate("window.scrollTo(0, 0)")  # the click above scrolled; the header sticks at the top
        w.page.wait_for_timeout(500)
        w.shot(out_dir / "dashboard.png", full_page=True)
        assert all(u.startswith(daemon.base_url) for u in w.urls), w.urls
        assert daemon.sigterm() == 0, daemon.tail()
    finally:
        daemon.cleanup()
