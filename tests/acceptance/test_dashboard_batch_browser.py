"""Issue #53 "Must show": the dashboard's batch page and the job list's outcome column in headless Chromium
(Debian's ``chromium`` through Playwright, as ``test_dashboard_browser``; skipped where it cannot be installed).

A real API server holds a batch of four jobs of one key, completed through the queue with summaries in the
worker's layout (both protocols, penetration, verification, the outcome): one executable, one not executable
with two reasons, one FAILED, one left QUEUED. The job list shows each job's outcome and its refined E_t / E_r
and filters by outcome; the batch page shows the counts per state and outcome, the aggregate metrics of both
protocols, the not executable sequence with its reasons, the failed job with its error, the report and its
links, and downloads the CSV report. ``HOI_REFINE_UPDATE_DOCS=1`` also saves the batch page and the job list as
docs/dashboard_batch.png and docs/dashboard_jobs.png.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from common.api_client import ApiClient
from common.api_key_store import ApiKeyStore
from common.sequence_io import sequence_to_npz_bytes
from tests.support.browser import CHROMIUM_ARGS, Deployment, use_key
from tests.support.queue_fixtures import fake_result, tiny_sequence
from tests.support.visual import DOCS, update_docs

if TYPE_CHECKING:
    from playwright.sync_api import FloatRect

pytestmark = pytest.mark.slow

JUMP = {"code": "recording_too_fast", "frame": 41, "value": 38.5, "unit": "deg/frame",
        "message": "The recorded object turns 38.5 deg between frames 40 and 41, faster than a grasp can follow."}
SLIP = {"code": "slipped", "frame": 44, "value": 31.2, "unit": "deg",
        "message": "The object turns out of the grasp: 31.2 deg off at frame 44."}  # fmt: skip


def summary(
    ref_t: float, ref_r: float, paper_t: float, paper_r: float, reasons: list[dict[str, Any]] | None
) -> dict[str, Any]:
    """A result summary in the worker's layout; ``reasons`` None: executable."""
    def stage(e_t: float, e_r: float, p_t: float, p_r: float, ok: bool) -> dict[str, Any]:
        return {"E_t": e_t, "E_r": e_r, "E_j": 1.1, "E_ft": 1.4, "success": ok, "max_E_t": 2 * e_t,
                "max_E_r": 2 * e_r, "penetration_mean_mm": 0.8, "penetration_max_mm": 3.1, "hand_only_fraction": 0.9,
                "paper": {"E_t": p_t, "E_r": p_r, "E_j": 1.2, "E_ft": 1.5, "success": ok, "penetration_max_mm": 3.1}}
    executable = reasons is None
    outcome = {"executable": executable, "protocol": "paper", "reasons": reasons or []}
    return {"kind": "refine", "outcome": outcome,
            "metrics": {"raw": stage(4.2, 35.0, 4.6, 38.0, False), "refined": stage(ref_t, ref_r, paper_t, paper_r,
                                                                                    executable),
                        "verification": {"verified": True}, "outcome": outcome}}  # fmt: skip


def _batch(dep: Deployment, key: str) -> tuple[str, dict[str, str]]:
    """A batch of four jobs submitted over HTTP and finished through the queue; returns its id and job ids."""
    from common.job_options import JobOptions

    with ApiClient(dep.base_url, key) as client:
        batch_id = client.create_batch("example-batch", {"split": "dev"})["id"]
        ids = {}
        for i, name in enumerate(("can-lift", "bowl-turn", "mug-broken", "box-waiting")):
            seq = tiny_sequence(seed=i, frames=12, name=name)
            ids[name] = client.submit(sequence_to_npz_bytes(seq), f"{name}.npz", JobOptions(seed=i), None,
                                      batch_id)["id"]  # fmt: skip
    results = {"can-lift": summary(0.41, 1.9, 0.48, 2.1, None),
               "bowl-turn": summary(2.4, 24.0, 2.9, 33.5, [JUMP, SLIP])}  # fmt: skip
    for name in ("can-lift", "bowl-turn", "mug-broken"):
        lease = dep.queue.claim("browser-test")
        assert lease is not None and lease.job_id == ids[name]
        if name in results:
            dep.queue.complete(lease.job_id, lease.lease_token, fake_result()[0], results[name])
        else:
            dep.queue.fail(lease.job_id, lease.lease_token, "the object mesh has no volume")
    return batch_id, ids


def test_the_batch_page_and_the_job_lists_outcome_column(chromium: str, deployment: Deployment, tmp_path: Path) -> None:
    from playwright.sync_api import expect, sync_playwright

    _, key = ApiKeyStore(deployment.engine).create("browser")
    batch_id, ids = _batch(deployment, key)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900}, accept_downloads=True)
            page.goto(deployment.base_url + "/ui")
            use_key(page, key)

            # The job list: outcome and refined E_t / E_r (the paper's protocol) per job.
            def row(name: str) -> Any:
                return page.locator(f'#jobs tr[data-job-id="{ids[name]}"]')

            expect(row("can-lift").locator(".outcome")).to_have_text("executable", timeout=20_000)
            expect(row("can-lift").locator("td.e-t")).to_have_text("0.48")
            expect(row("can-lift").locator("td.e-r")).to_have_text("2.10")
            expect(row("bowl-turn").locator(".outcome")).to_have_text("not executable")
            expect(row("bowl-turn").locator("td.e-r")).to_have_text("33.50")
            tip = row("bowl-turn").locator(".outcome").get_attribute("title") or ""
            assert "recording_too_fast at frame 41" in tip
            expect(row("mug-broken").locator(".outcome")).to_have_count(0)  # FAILED: no outcome
            expect(row("box-waiting").locator("td.state")).to_have_text("QUEUED")
            if update_docs():
                top: FloatRect = {"x": 0, "y": 0, "width": 1200, "height": 400}
                page.screenshot(path=str(DOCS / "dashboard_jobs.png"), clip=top)
            page.select_option("#outcome-filter", "not_executable")  # asks the API for that outcome only
            expect(page.locator("#jobs tbody tr")).to_have_count(1, timeout=10_000)
            expect(row("bowl-turn")).to_have_count(1)
            page.select_option("#outcome-filter", "")

            # The batches list leads to the batch page.
            page.click("text=Batches")
            batch_row = page.locator(f'#batches tr[data-batch-id="{batch_id}"]')
            expect(batch_row.locator("td").nth(4)).to_have_text("1", timeout=10_000)  # executable
            batch_row.locator("a").click()
            expect(page.locator("#batch-title")).to_contain_text("example-batch")
            expect(page.locator("#batch-state")).to_have_text("ACTIVE")
            cards = page.locator("#batch-counts")
            expect(cards.locator('[data-count="total"] b')).to_have_text("4")
            expect(cards.locator('[data-outcome="executable"] b')).to_have_text("1")
            expect(cards.locator('[data-outcome="not_executable"] b')).to_have_text("1")
            expect(cards.locator('[data-state="FAILED"] b')).to_have_text("1")
            expect(cards.locator('[data-state="QUEUED"] b')).to_have_text("1")
            # The aggregate over the two succeeded sequences, both protocols and penetration.
            agg = page.locator("#batch-metrics")
            expect(agg.locator('tr[data-metric="paper.E_t"] td').nth(2)).to_have_text(f"{(0.48 + 2.9) / 2:.2f}")
            expect(agg.locator('tr[data-metric="paper.SR"] td').nth(2)).to_have_text("50 %")
            expect(agg.locator('tr[data-metric="all_frames.E_r"] td').nth(1)).to_have_text("35.00")
            expect(agg.locator('tr[data-metric="all_frames.penetration_max_mm"] td').nth(2)).to_have_text("3.10")
            # The sequence that is not executable, with its reasons; the failed job with its error.
            failures = page.locator(f'#batch-failures tr[data-job-id="{ids["bowl-turn"]}"]')
            expect(failures.locator("li")).to_have_count(2)
            expect(failures.locator('li[data-code="recording_too_fast"]')).to_contain_text(
                "at frame 41 (38.5 deg/frame): The recorded object turns 38.5 deg")
            expect(failures.locator('li[data-code="slipped"]')).to_contain_text("at frame 44 (31.2 deg)")
            expect(page.locator(f'#batch-errors tr[data-job-id="{ids["mug-broken"]}"]')).to_contain_text(
                "the object mesh has no volume")
            expect(page.locator("#batch-jobs tbody tr")).to_have_count(4)
            # Links and the report: the CSV downloads with the outcome first.
            expect(page.locator('#batch-links tr[data-rel="report_parquet"]')).to_contain_text(
                f"GET /v1/batches/{batch_id}/report?format=parquet")
            expect(page.locator('#batch-links tr[data-rel="not_executable"]')).to_contain_text("outcome=not_executable")
            with page.expect_download() as got:
                page.click('#batch-downloads button[data-format="csv"]')
            report = tmp_path / "report.csv"
            got.value.save_as(report)
            bowl = {r["name"]: r for r in csv.DictReader(io.StringIO(report.read_text()))}["bowl-turn"]
            assert (bowl["outcome"], bowl["reason"]) == ("not_executable", "recording_too_fast")
            if update_docs():
                page.screenshot(path=str(DOCS / "dashboard_batch.png"), full_page=True)

            # From the batch page to a job: its outcome with the reasons, the paper's protocol and penetration.
            failures.locator("a").click()
            expect(page.locator("#job-outcome")).to_have_text("not executable", timeout=10_000)
            expect(page.locator("#job-reasons li")).to_have_count(2)
            metrics = page.locator("#metrics")
            expect(metrics.locator('tr[data-metric="paper.E_t"] td').nth(2)).to_have_text("2.90", timeout=10_000)
            expect(metrics.locator('tr[data-metric="paper.success"] td').nth(2)).to_have_text("no")
            expect(metrics.locator('tr[data-metric="penetration_max_mm"] td').nth(2)).to_have_text("3.10")
            expect(page.locator("#verification")).to_contain_text("verified")
            expect(page.locator("#job-batch a")).to_have_attribute("href", f"#/batches/{batch_id}")
        finally:
            browser.close()
