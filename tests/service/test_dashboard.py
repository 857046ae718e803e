"""The dashboard in a real (headless) Chromium: submit a demo job, watch it fill in."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from tests.service.helpers import LiveServer, settings_for

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


# (size, extra form fields, what the statistics table must show)
REFERENCE_JOB = ("tiny", {}, "primary rays")
# Proxy mode on 2 shards with the shipped proxies: the per-mesh plan is shown.
PROXY_JOB = ("small", {"shards": 2, "band": 0.2}, "width 16")


@pytest.mark.slow
@pytest.mark.parametrize("job", [REFERENCE_JOB, PROXY_JOB], ids=["reference", "proxy"])
def test_dashboard_submits_demo_job_and_shows_progress_and_image(tmp_path, job):
    size, fields, expected = job
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
            page.select_option("select[name=size]", size)
            if fields:
                page.select_option("select[name=mode]", "proxy")
            form = {"width": 64, "height": 48, "spp": 4, "tile_size": 16, **fields}
            for name, value in form.items():
                page.fill(f"input[name={name}]", str(value))
            page.click("#submit-button")

            expect(page.locator("#job-view")).to_be_visible()
            expect(page.locator("#job-state")).to_have_text("succeeded", timeout=60_000)
            expect(page.locator("#job-progress")).to_have_attribute("aria-valuenow", "100")
            expect(page.locator("#job-progress-text")).to_have_text("100%")
            page.wait_for_function("() => document.querySelector('#job-image').naturalWidth"
                                   " === 64", timeout=20_000)
            expect(page.locator("#phase-svg rect").first).to_be_visible()
            expect(page.locator("#stats-table")).to_contain_text(expected)
            if fields:  # the form's proxy knobs reached the job
                job_id = page.url.rsplit("/", 1)[-1]
                sent = httpx.get(f"{server.url}/v1/jobs/{job_id}").json()["settings"]
                assert sent["mode"] == "proxy" and sent["shards"] == 2, sent
                assert sent["proxy"]["band"] == 0.2, sent
            expect(page.locator("#cancel-button")).to_be_disabled()
            shot = tmp_path / f"dashboard-job-{size}.png"
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
