"""The dashboard in a real (headless) Chromium: submit a demo job, watch it fill in."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.service.helpers import LiveServer, settings_for

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


@pytest.mark.slow
def test_dashboard_submits_demo_job_and_shows_progress_and_image(tmp_path):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (apt-get install -y chromium); the dashboard "
                    "test needs Debian's Chromium and never downloads a browser")
    from playwright.sync_api import expect, sync_playwright

    with LiveServer(settings_for(tmp_path)) as server, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            external = []  # nothing may be fetched from outside the service
            page.on("request", lambda r: None if r.url.startswith(server.url)
                    else external.append(r.url))
            page.goto(server.url + "/")
            expect(page.locator("#scene-select option[value=forest]")).to_have_count(1)
            page.select_option("#scene-select", "forest")
            page.select_option("select[name=size]", "tiny")
            for name, value in {"width": 64, "height": 48, "spp": 4, "tile_size": 16}.items():
                page.fill(f"input[name={name}]", str(value))
            page.click("#submit-button")

            expect(page.locator("#job-view")).to_be_visible()
            expect(page.locator("#job-state")).to_have_text("succeeded", timeout=60_000)
            expect(page.locator("#job-progress")).to_have_attribute("aria-valuenow", "100")
            expect(page.locator("#job-progress-text")).to_have_text("100%")
            page.wait_for_function("() => document.querySelector('#job-image').naturalWidth"
                                   " === 64", timeout=20_000)
            expect(page.locator("#phase-svg rect").first).to_be_visible()
            expect(page.locator("#stats-table")).to_contain_text("primary rays")
            expect(page.locator("#cancel-button")).to_be_disabled()
            shot = tmp_path / "dashboard-job.png"
            page.screenshot(path=str(shot), full_page=True)
            print(f"dashboard screenshot: {shot}")

            page.goto(server.url + "/#/")
            row = page.locator("#job-table tbody tr").first
            expect(row.locator(".state")).to_have_text("succeeded")
            expect(row.locator("[role=progressbar]")).to_have_attribute("aria-valuenow", "100")
            page.screenshot(path=str(tmp_path / "dashboard-list.png"), full_page=True)
            assert external == []
        finally:
            browser.close()
