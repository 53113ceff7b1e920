"""The dashboard's actions and its agreement, in a real headless Chromium (Playwright with Debian's
chromium, launched as tests/test_e2e_dashboard.py launches it) against the assembled daemon and its
simulated cell, in-process so that a test can unplug a grating or latch a fault in the loop.

Through the page, as people on the line do: a viewer sees no buttons; an engineer drops a campaign
(stored) and a broken one (refused by row and column, the cell at fault outlined); an operator drops
a target file and fills the target form (queued; refusals named); a latched fault is reset through
a confirmation that shows its reason; the grating calibration runs with its progress shown. And
what the page shows agrees with itself at every moment: the banner's grating lines and the joint
table's encoder column, the RSI panel's header and its stop box; the stops table keeps each stop's
detail whole inside its panel.

Without ``/usr/bin/chromium`` the module is skipped, except in CI (``CI=true``).
Angles in degrees, times in seconds.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import pytest_asyncio
from e2e_daemon import TOKENS, in_process_cell
from test_e2e_dashboard import CHROMIUM, CHROMIUM_ARGS, _need_chromium
from test_e2e_faults import until
from test_service_api import campaign_csv

from comp_daemon.daemon.app import Daemon
from comp_daemon.rt.safety import FaultKind, SafetyState

pytestmark = [pytest.mark.slow, pytest.mark.asyncio(loop_scope="module")]

REFUSED_REQUEST = "Failed to load resource: the server responded with a status of 422"

# One look at the page, taken in one go: the banner's grating joints, the joints the table shows
# with a grating that is not ok, the RSI panel's header word and whether its stop box shows.
LOOK = """() => {
  const reasons = document.getElementById('reasons');
  const banner = reasons.classList.contains('hidden') ? [] : [...reasons.querySelectorAll('li')]
    .map((li) => li.textContent).filter((t) => /^grating A\\d+: /.test(t))
    .map((t) => Number(t.match(/A(\\d+)/)[1]));
  const table = [...document.querySelectorAll('#joints tbody tr')].filter((tr) => {
    const p = tr.cells[6].querySelector('.pill');
    return p && !['ok', 'absent'].includes(p.textContent);
  }).map((tr) => Number(tr.cells[0].textContent.slice(1)));
  return {
    banner: banner.sort(), table: table.sort(), header: document.getElementById('cycle').textContent,
    box: !document.getElementById('rsi-stop').classList.contains('hidden'),
    ready: document.getElementById('ready-text').textContent,
  };
}"""


class Cell:
    """The module's daemon with its simulated cell, a browser, and an HTTP client per role."""

    def __init__(self, daemon: Daemon, browser: Any, home: np.ndarray) -> None:
        self.daemon = daemon
        self.browser = browser
        self.home = home
        self.base_url = f"http://127.0.0.1:{daemon.http_port}"

    def client(self, role: str) -> httpx.AsyncClient:
        return httpx.AsyncClient(
            base_url=self.base_url, headers={"Authorization": f"Bearer {TOKENS[role]}"}, timeout=10.0
        )

    async def page(self, role: str, routes: dict[str, Any] | None = None) -> Any:
        """The dashboard as ``role``, live unless ``routes`` answers API paths (with their query)
        with the given JSON instead of the service."""
        from playwright.async_api import expect

        page = await self.browser.new_page(viewport={"width": 1600, "height": 1000})
        if routes:

            async def answer(route: Any) -> None:
                url = route.request.url
                doc = next((d for path, d in routes.items() if url.endswith(path)), None)
                await (route.continue_() if doc is None else route.fulfill(json=doc))

            await page.route("**/api/**", answer)
        page.errors = []

        def console(m: Any) -> None:
            # the browser logs each refused request (422) itself; the page shows the refusal
            if m.type == "error" and not m.text.startswith(REFUSED_REQUEST):
                page.errors.append(m.text)

        page.on("console", console)
        page.on("pageerror", lambda e: page.errors.append(f"page error: {e}"))
        await page.goto(f"{self.base_url}/dashboard/#token={TOKENS[role]}")
        if not routes:  # with routes the browser holds each response until it ends: no event stream
            await expect(page.locator("#live-text")).to_have_text("live", timeout=15_000)
        await expect(page.locator("#p-actions")).to_be_visible(timeout=10_000)
        return page

    def target_rows(self, shifts: list[float]) -> str:
        lines = ["pose_id,a1,a2,a3,a4,a5,a6"]
        for k, d in enumerate(shifts):
            a = self.home + np.r_[d, 0.5 * d, 0.0, 0.0, 0.0, 0.0]
            lines.append(",".join([f"rib-{k + 1:02d}", *(f"{v:.4f}" for v in a)]))
        return "\n".join(lines) + "\n"

    async def idle(self, timeout_s: float = 60.0) -> None:
        """Until no target runs and the cell is ready for one."""
        executor = self.daemon.targets.executor
        assert executor is not None
        async with self.client("viewer") as c:

            async def open_targets() -> int:
                r = await c.get("/api/status")
                counts = r.json()["targets"]
                return sum(counts.get(s, 0) for s in ("queued", "compensating", "moving", "settling"))

            async with asyncio.timeout(timeout_s):
                while await open_targets() or executor.current_target_id is not None:
                    await asyncio.sleep(0.1)
        await until(lambda: not self.daemon.view.readiness_reasons(), 15)


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def cell(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Cell]:
    _need_chromium()
    from playwright.async_api import async_playwright

    root: Path = tmp_path_factory.mktemp("dashboard-actions")
    async with in_process_cell(root, seed=11, rearm_after_s=2.0) as daemon:
        assert daemon.sim_info is not None
        async with async_playwright() as pw:
            browser = await pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
            try:
                yield Cell(daemon, browser, np.array(daemon.sim_info.home_deg))
            finally:
                await browser.close()


async def drop_file(page: Any, name: str, text: str, mime: str = "text/csv") -> None:
    """Drop a file on the page's drop zone as a browser does (a drop event with its DataTransfer)."""
    transfer = await page.evaluate_handle(
        """([name, text, mime]) => {
          const dt = new DataTransfer();
          dt.items.add(new File([text], name, { type: mime }));
          return dt;
        }""",
        [name, text, mime],
    )
    await page.locator("#drop").dispatch_event("drop", {"dataTransfer": transfer})


async def sample(page: Any, seconds: float, every_s: float = 0.05) -> list[dict[str, Any]]:
    looks = []
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while loop.time() < end:
        looks.append(await page.evaluate(LOOK))
        await asyncio.sleep(every_s)
    return looks


def assert_agree(looks: list[dict[str, Any]]) -> None:
    for look in looks:
        assert look["banner"] == look["table"], look
        assert look["header"].endswith("stopped") == look["box"], look
        if look["banner"]:
            assert look["ready"] == "not ready", look


# ------------------------------------------------------------------------------------------- roles


async def test_a_viewer_sees_no_buttons_an_operator_no_engineer_action(cell: Cell) -> None:
    from playwright.async_api import expect

    viewer = await cell.page("viewer")
    try:
        await expect(viewer.locator("#fault-text")).not_to_have_text("—", timeout=10_000)
        assert await viewer.locator("main button:visible").count() == 0
        for hidden in ("#a-upload", "#a-target", "#reset-btn", "#calibrate-btn", "#drop"):
            await expect(viewer.locator(hidden)).to_be_hidden()
        await expect(viewer.locator("#grating-text")).to_contain_text("in use: version")
        assert viewer.errors == []
    finally:
        await viewer.close()

    operator = await cell.page("operator")
    try:
        for shown in ("#drop", "#target-form", "#reset-btn"):
            await expect(operator.locator(shown)).to_be_visible()
        await expect(operator.locator("#calibrate-btn")).to_be_hidden()
        await expect(operator.locator("#reset-btn")).to_be_disabled()  # no fault latched
        # a campaign needs an engineer: the page says so and sends nothing
        await drop_file(operator, "campaign.csv", campaign_csv(n=30))
        await expect(operator.locator("#upload-result")).to_contain_text("needs the engineer role")
        assert operator.errors == []
    finally:
        await operator.close()


# ------------------------------------------------------------------------------------------ upload


async def test_an_engineer_drops_a_campaign_and_a_broken_one(cell: Cell) -> None:
    from playwright.async_api import expect

    page = await cell.page("engineer")
    try:
        await drop_file(page, "cell-campaign-2026-12.csv", campaign_csv(n=40, seed=3))
        result = page.locator("#upload-result")
        await expect(result).to_contain_text("stored as data set", timeout=15_000)
        await expect(result).to_contain_text("40 rows, 30 fit / 10 check")
        await expect(page.locator("#datasets tbody")).to_contain_text(
            "cell-campaign-2026-12.csv", timeout=10_000
        )

        lines = campaign_csv(n=40, seed=4).splitlines()
        cells = lines[3].split(",")
        cells[2] = "500"  # a3 of the file's row 4 (header = row 1)
        lines[3] = ",".join(cells)
        await drop_file(page, "broken.csv", "\n".join(lines) + "\n")
        refusal = page.locator("[data-testid=refusal]")
        await expect(refusal).to_contain_text("broken.csv refused at row 4, column a3", timeout=15_000)
        await expect(refusal).to_contain_text("outside the axis limits")
        bad = page.locator("[data-testid=refusal-excerpt] td.bad-cell")
        await expect(bad).to_have_count(1)
        await expect(bad).to_have_text("500")
        await expect(page.locator("[data-testid=refusal-excerpt] tr.bad-row td").first).to_have_text("4")
        async with cell.client("viewer") as c:
            names = [d["name"] for d in (await c.get("/api/datasets")).json()]
        assert "broken.csv" not in names and "cell-campaign-2026-12.csv" in names
        assert page.errors == []
    finally:
        await page.close()


# ------------------------------------------------------------------------------------------ queue


async def test_an_operator_queues_a_target_file_and_a_target_from_the_form(cell: Cell) -> None:
    from playwright.async_api import expect

    await cell.idle()
    page = await cell.page("operator")
    try:
        await drop_file(page, "rib-7.csv", cell.target_rows([-3.0, 3.0]))
        result = page.locator("#upload-result")
        await expect(result).to_contain_text("rib-7.csv: 2 targets queued as batch", timeout=15_000)
        await page.locator("#show-finished").check()
        await expect(page.locator("#targets tbody")).to_contain_text("rib-02", timeout=10_000)

        broken = cell.target_rows([-3.0, 3.0]).splitlines()
        fields = broken[2].split(",")
        fields[3] = "500"  # a3 of row 3
        broken[2] = ",".join(fields)
        await drop_file(page, "rib-8.csv", "\n".join(broken) + "\n")
        await expect(page.locator("[data-testid=refusal]")).to_contain_text(
            "rib-8.csv refused at row 3, column a3", timeout=15_000
        )
        await expect(page.locator("[data-testid=refusal-excerpt] td.bad-cell")).to_have_text("500")

        # the form: the current axes (where the robot stands once the dropped targets have run), A1
        # moved by 2°, queued
        await cell.idle()
        standing = {j.joint: j.axis_deg for j in cell.daemon.view.snapshot().joints}
        await page.wait_for_timeout(1500)  # the page's snapshot follows the daemon's
        await page.locator("#t-current").click()
        a1 = float(await page.locator("#t-a1").input_value())
        assert standing[1] is not None and abs(a1 - standing[1]) < 0.5
        await page.locator("#t-a1").fill(f"{a1 + 2.0:.4f}")
        await page.locator("#t-pose").fill("form-01")
        await page.locator("#t-queue").click()
        await expect(page.locator("#target-result")).to_contain_text("(form-01) queued", timeout=10_000)
        await expect(page.locator("#targets tbody")).to_contain_text("form-01", timeout=10_000)

        # a refused field is named and outlined; nothing is queued
        await page.locator("#t-a3").fill("500")
        await page.locator("#t-pose").fill("form-02")
        await page.locator("#t-queue").click()
        await expect(page.locator("#target-result")).to_contain_text("refused at field a3", timeout=10_000)
        await expect(page.locator("#t-a3")).to_have_class("bad")
        await cell.idle()
        async with cell.client("viewer") as c:
            targets = (await c.get("/api/targets", params={"newest_first": "true", "limit": 10})).json()
        by_pose = {t["request"].get("pose_id"): t for t in targets}
        assert {"rib-01", "rib-02", "form-01"} <= set(by_pose) and "form-02" not in by_pose
        assert by_pose["form-01"]["request"]["a1"] == pytest.approx(a1 + 2.0, abs=1e-4)
        # queued and run by the cell (whether each settles within tolerance on a loaded machine is
        # the executor's tests' business)
        states = {p: (by_pose[p]["state"], by_pose[p]["reason"]) for p in ("rib-01", "rib-02", "form-01")}
        assert all(state in ("done", "failed") for state, _ in states.values()), states
        assert all(by_pose[p]["commanded_axes_deg"] is not None for p in states), by_pose
        assert page.errors == []
    finally:
        await page.close()


# ------------------------------------------------------------------------------- agreement, reset


async def test_banner_table_and_stop_box_agree_and_a_fault_is_reset_through_the_page(cell: Cell) -> None:
    from playwright.async_api import expect

    await cell.idle()
    sim = cell.daemon.sim
    assert sim is not None
    page = await cell.page("operator")
    try:
        looks = await sample(page, 0.5)
        assert looks[-1]["banner"] == [] and looks[-1]["ready"] == "ready", looks[-1]

        # a grating unplugged and plugged back: the banner and the table say the same at every look
        await sim.command("unplug 1")
        looks = await sample(page, 3.0)
        await sim.command("replug 1")
        looks += await sample(page, 4.0)
        assert_agree(looks)
        assert any(look["banner"] == [1] for look in looks), looks[::10]
        assert looks[-1]["banner"] == [] and looks[-1]["table"] == [], looks[-1]
        await until(lambda: not cell.daemon.view.readiness_reasons(), 15)

        # a stop fault latched in the loop: Stop = 1, the controller stops RSI
        runtime = cell.daemon.realtime.runtime
        assert runtime is not None
        reason = "the error on A2 grew from 0.002 to 0.009 deg while correcting"
        runtime.fault(FaultKind.DIVERGING, reason)
        await expect(page.locator("#fault-text")).to_contain_text(reason, timeout=10_000)
        await expect(page.locator("#reset-btn")).to_be_enabled()
        looks = await sample(page, 3.0)
        await expect(page.locator("#rsi-stop")).to_be_visible(timeout=10_000)
        await expect(page.locator("#cycle")).to_contain_text("stopped")
        looks += await sample(page, 1.0)
        assert any(look["box"] for look in looks)

        # the stops table: each stop's detail whole, inside the panel
        async with cell.client("viewer") as c:
            last = (await c.get("/api/status")).json()["rsi"]["stops"][0]
        await expect(page.locator("#rsi-stops .detail").first).to_have_text(last["detail"])
        await expect(page.locator("#rsi-stops .then").first).to_have_text(last["next"])
        widths = await page.evaluate(
            "() => [document.getElementById('rsi-stops').scrollWidth,"
            " document.querySelector('#p-loop .body').clientWidth]"
        )
        assert widths[0] <= widths[1], widths

        # reset through the page: a confirmation with the fault's reason, then the loop is clear
        await page.locator("#reset-btn").click()
        dialog = page.locator("#confirm")
        await expect(dialog).to_be_visible()
        await expect(dialog).to_contain_text(reason)
        await page.locator("#confirm-ok").click()
        await expect(page.locator("#fault-result")).to_contain_text("diverging (stop) reset", timeout=10_000)
        await expect(page.locator("#fault-text")).to_contain_text("no fault latched", timeout=10_000)
        assert runtime.core.state is not SafetyState.FAULT
        # the simulated controller re-arms RSI 2 s after its stop; the header and the box follow together
        looks += await sample(page, 6.0)
        await expect(page.locator("#cycle")).to_contain_text("running", timeout=15_000)
        await expect(page.locator("#rsi-stop")).to_be_hidden()
        assert_agree(looks)
        async with cell.client("viewer") as c:
            kinds = [
                e["kind"] for e in (await c.get("/api/events/log", params={"newest_first": "true"})).json()
            ]
        assert "loop.fault_reset" in kinds
        assert page.errors == []
    finally:
        await page.close()
    await until(lambda: not cell.daemon.view.readiness_reasons(), 20)


# ---------------------------------------------------------------------------------------- gratings


async def test_an_engineer_calibrates_the_gratings_and_sees_the_progress(cell: Cell) -> None:
    from playwright.async_api import expect

    await cell.idle()
    runtime = cell.daemon.realtime.runtime
    assert runtime is not None and runtime.calibration is not None
    version = runtime.calibration.version
    page = await cell.page("engineer")
    try:
        await expect(page.locator("#grating-text")).to_contain_text(
            f"in use: version {version}", timeout=10_000
        )
        await page.locator("#calibrate-btn").click()
        await expect(page.locator("#confirm")).to_be_visible()
        await page.locator("#confirm-ok").click()
        seen: list[str] = []
        loop = asyncio.get_running_loop()
        end = loop.time() + 180
        while loop.time() < end:
            progress, text = await page.evaluate(
                "() => [document.querySelector('[data-testid=grating-progress]')?.textContent ?? null,"
                " document.getElementById('grating-text').textContent]"
            )
            if progress is not None:
                seen.append(progress)
            elif seen and f"version {version + 1}" in text:
                break
            await asyncio.sleep(0.1)
        measured = [int(t.split(": ")[1].split(" of ")[0]) for t in seen if " of " in t]
        assert measured == sorted(measured) and any(0 < k < 6 for k in measured), seen
        assert all(t.endswith(" of 6 poses measured") for t in seen if " of " in t), seen
        await expect(page.locator("#grating-text")).to_contain_text(
            f"in use: version {version + 1}", timeout=10_000
        )
        await expect(page.locator("#calibrate-btn")).to_be_enabled(timeout=10_000)
        assert page.errors == []
    finally:
        await page.close()


# ------------------------------------------------------------------------------- jobs and ladder

REPORT = {
    "unmodelled": ["backlash"],
    "joints": [2, 3],
    "noise_floor_mm": 0.01,
    "unexplained_rms_mm": 0.02,
    "rows": {"fit": 120, "check": 40},
    "where": {"summary": "Backlash on A2 and on A3. Approach the targets from one side."},
    "baseline": {"check_rms_mm": 0.40, "check_max_mm": 0.90},
    "steps": [
        {"effect": "geometric", "joints": [], "check_rms_mm": 0.20, "check_max_mm": 0.50,
         "shrink_pct": 50.0, "significant": True},
        {"effect": "backlash", "joints": [2], "check_rms_mm": 0.08, "check_max_mm": 0.20,
         "shrink_pct": 60.0, "significant": True},
        {"effect": "backlash", "joints": [3], "check_rms_mm": 0.03, "check_max_mm": 0.07,
         "shrink_pct": 62.5, "significant": True},
    ],
}  # fmt: skip
JOB = {
    "id": 1, "kind": "diagnosis", "state": "done", "progress": 1.0, "message": "writing the report",
    "params": {}, "dataset_id": 1, "result": None, "error": None,
    "created_at": None, "started_at": None, "finished_at": None,
}  # fmt: skip


async def test_an_ended_job_says_so_and_ladder_steps_are_named_with_their_joints(cell: Cell) -> None:
    """The page's rendering of a finished diagnosis (the service's answers given, in the API's shapes):
    its job no longer reads as its last progress message, and two backlash steps on different
    joints are told apart in the table and the chart."""
    from playwright.async_api import expect

    routes = {"/api/jobs?limit=15": [JOB], "/api/diagnoses?limit=10": [JOB], "/api/diagnoses/1": REPORT}
    page = await cell.page("viewer", routes)
    try:
        row = page.locator("#jobs tbody tr")
        await expect(row).to_have_count(1, timeout=10_000)
        await expect(row).to_contain_text("report ready")
        await expect(row).not_to_contain_text("writing the report")
        await page.locator("#diagnoses tbody tr").first.click()
        steps = page.locator("#ladder tbody tr td:first-child")
        await expect(steps).to_have_text(
            ["nominal", "geometric", "backlash A2", "backlash A3"], timeout=10_000
        )
        chart = await page.locator("#ladder-chart text").all_text_contents()
        assert "backlashA2" in chart and "backlashA3" in chart, chart
        assert page.errors == []
    finally:
        await page.close()


RUNNING_FIT = {
    **JOB, "id": 2, "kind": "fit", "state": "running", "progress": 0.05, "params": {"model": "chebyshev:cv"},
    "message": "fitting chebyshev:cv (order by cross-validation): cross-validation fits 12 of 50, 38 to go",
}  # fmt: skip


async def test_a_running_fit_says_which_model_and_how_many_steps_remain(cell: Cell) -> None:
    """A fit job making its cross-validation fits: the note names the model and the step, the line
    under the bar how many are done and remain; an ended job has no such line."""
    from playwright.async_api import expect

    page = await cell.page("viewer", {"/api/jobs?limit=15": [RUNNING_FIT, JOB]})
    try:
        rows = page.locator("#jobs tbody tr")
        await expect(rows).to_have_count(2, timeout=10_000)
        await expect(rows.nth(0).locator("td.reason")).to_have_text(
            "fitting chebyshev:cv (order by cross-validation) — cross-validation fits"
        )
        await expect(rows.nth(0).get_by_test_id("job-step")).to_have_text("12/50, 38 to go")
        await expect(rows.nth(1).get_by_test_id("job-step")).to_have_count(0)
        assert page.errors == []
    finally:
        await page.close()
