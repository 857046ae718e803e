"""The dashboard in a real (headless) Chromium against a live server: the job list, the job
page (settings, times, explanation, tiles, image, log, shards, phases), actions, upload and
the A/B view. Each test saves screenshots under its tmp_path."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest

from tests.service.helpers import TINY, HeldSlots, LiveServer, settings_for, two_box_glb, wait_for

pytestmark = pytest.mark.slow

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
JOB_TIMEOUT_MS = 90_000
FORM = {"width": 64, "height": 48, "spp": 4, "tile_size": 16}
# A sharded pair on the shipped proxies: the exact job, then the proxy job to compare.
SHARDED = {**TINY, "width": 64, "height": 48, "shards": 2, "seed": 3}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (apt-get install -y chromium); the dashboard "
                    "tests need Debian's Chromium and never download a browser")
    with LiveServer(settings_for(tmp_path_factory.mktemp("dash"))) as s:
        yield s


@pytest.fixture(scope="module")
def browser(server):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def api(server):
    with httpx.Client(base_url=server.url, timeout=30.0) as c:
        yield c


class Watched:
    """A page plus what it did: requests, failed responses, script errors."""

    def __init__(self, page, base_url: str):
        self.page, self.requests, self.bad, self.errors = page, [], [], []
        page.on("request", lambda r: self.requests.append(r.url))
        page.on("response", lambda r: r.status >= 400 and self.bad.append(f"{r.status} {r.url}"))
        page.on("pageerror", lambda e: self.errors.append(str(e)))
        page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        self.base_url = base_url

    def check_clean(self):
        assert (self.errors, self.bad) == ([], [])
        assert all(u.startswith(self.base_url) for u in self.requests)  # nothing external


@pytest.fixture
def watched(browser, server):
    context = browser.new_context(viewport={"width": 1280, "height": 1000})
    context.add_init_script("""
        window.__explains = [];
        new MutationObserver(() => {
          const e = document.querySelector('#job-explain');
          if (e && e.textContent) window.__explains.push(e.textContent);
        }).observe(document, {subtree: true, childList: true, characterData: true});
    """)
    w = Watched(context.new_page(), server.url)
    yield w
    context.close()


def _done(api, job_id: str) -> dict:
    return wait_for(lambda: (j := api.get(f"/v1/jobs/{job_id}").json())["state"]
                    in ("succeeded", "failed", "canceled") and j, 120, what=f"{job_id} ends")


def _canvas_mean(page, selector: str) -> float:
    """Mean of the RGB bytes the canvas shows."""
    return page.evaluate("""(sel) => {
        const c = document.querySelector(sel);
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let s = 0; for (let i = 0; i < d.length; i += 4) s += d[i] + d[i + 1] + d[i + 2];
        return s / (3 * d.length / 4); }""", selector)


def test_job_page_from_the_form_draws_tiles_settings_times_log(server, watched, api, tmp_path):
    from playwright.sync_api import expect

    page = watched.page
    page.goto(server.url + "/")
    expect(page.locator("#scene-select option[value=forest]")).to_have_count(1)
    page.select_option("#scene-select", "forest")
    page.select_option("select[name=size]", "tiny")
    expect(page.locator("label.proxy-knob").first).to_be_hidden()  # exact mode: no proxy knobs
    for name, value in FORM.items():
        page.fill(f"input[name={name}]", str(value))
    page.click("#submit-button")

    expect(page.locator("#job-view")).to_be_visible()
    expect(page.locator("#job-state")).to_have_text("succeeded", timeout=JOB_TIMEOUT_MS)
    expect(page.locator("#job-progress")).to_have_attribute("aria-valuenow", "100")
    settings = page.locator("#settings-table")
    expect(settings.locator("tr[data-key=resolution] td").nth(1)).to_have_text("64 × 48")
    expect(settings.locator("tr[data-key='samples per pixel'] td").nth(1)).to_have_text(
        "4 (2 per pass)")
    expect(settings.locator("tr[data-key='proxy band']")).to_have_count(0)
    times = page.locator("#times-table")
    for key in ("created", "started", "finished"):
        expect(times.locator(f"tr[data-key={key}] td").nth(1)).not_to_have_text("–")
    expect(times.locator("tr[data-key=duration] td").nth(1)).to_contain_text(" s")
    expect(page.locator("#tile-svg rect[data-samples='4']")).to_have_count(4 * 3)
    expect(page.locator("#log-view")).to_contain_text("preparing scene 'forest:tiny'")
    expect(page.locator("#log-status")).to_have_text("complete (job succeeded)")
    expect(page.locator("#phase-svg rect").first).to_be_visible()
    expect(page.locator("#phase-caption")).to_contain_text("single-process render")
    expect(page.locator("#phase-chart")).not_to_contain_text("null")
    expect(page.locator("#shard-panel")).to_contain_text("no shards")
    expect(page.locator("#cancel-button")).to_be_hidden()
    expect(page.locator("#requeue-button")).to_be_visible()
    expect(page.locator("#image-empty")).to_be_hidden()
    expect(page.locator("#downloads")).to_be_visible()

    # The image came from tile events and one /pixels read of the final image (plus one at
    # open when the page joined a job with passes done): no PNGs, no read per tile.
    assert not [u for u in watched.requests if "image.png" in u]
    reads = len([u for u in watched.requests if u.endswith("/pixels")])
    tiles = 4 * 3  # tile rects of this job: a read per tile would be at least this many
    assert reads in (1, 2), f"{reads} /pixels reads for {tiles} tiles"
    canvas = page.locator("#job-canvas")
    assert page.evaluate("document.querySelector('#job-canvas').width") == 64
    base = _canvas_mean(page, "#job-canvas")
    assert base > 1.0
    page.locator("#exposure").fill("2")
    expect(page.locator("#exposure-value")).to_have_text("+2.0 EV")
    assert _canvas_mean(page, "#job-canvas") > base * 1.2
    page.select_option("#zoom", "4")
    assert canvas.bounding_box()["width"] == pytest.approx(256, abs=1)
    page.screenshot(path=str(tmp_path / "job-page.png"), full_page=True)
    watched.check_clean()


def test_queued_then_preparing_job_explains_itself_without_broken_links(server, watched, api,
                                                                         tmp_path):
    from playwright.sync_api import expect

    held = HeldSlots(server.url, server.settings.max_concurrent_jobs)
    try:
        job = api.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()
        page = watched.page
        page.goto(f"{server.url}/#/jobs/{job['id']}")
        expect(page.locator("#job-state")).to_have_text("queued")
        expect(page.locator("#job-explain")).to_contain_text("Queued: waiting for a free job")
        expect(page.locator("#image-empty")).to_be_visible()
        expect(page.locator("#downloads")).to_be_hidden()
        expect(page.locator("#job-canvas")).to_be_hidden()
        expect(page.locator("#cancel-button")).to_be_visible()
        expect(page.locator("#delete-button")).to_be_hidden()
        page.screenshot(path=str(tmp_path / "queued.png"), full_page=True)
    finally:
        held.release()
    expect(page.locator("#job-state")).to_have_text("succeeded", timeout=JOB_TIMEOUT_MS)
    explains = page.evaluate("window.__explains")
    assert any(e.startswith("Preparing: loading scene forest:tiny") for e in explains), explains
    watched.check_clean()


def test_cancel_requeue_delete_fit_the_state(server, watched, api, tmp_path):
    from playwright.sync_api import expect

    page = watched.page
    page.on("dialog", lambda d: d.accept())
    held = HeldSlots(server.url, server.settings.max_concurrent_jobs)
    try:
        job = api.post("/v1/jobs", json={"scene": "forest:tiny", **TINY, "seed": 7}).json()
        page.goto(f"{server.url}/#/jobs/{job['id']}")
        page.click("#cancel-button")
        expect(page.locator("#job-state")).to_have_text("canceled")
        expect(page.locator("#cancel-button")).to_be_hidden()
        expect(page.locator("#requeue-button")).to_be_visible()
        page.screenshot(path=str(tmp_path / "canceled.png"), full_page=True)
    finally:
        held.release()
    page.click("#requeue-button")
    page.wait_for_url(lambda url: job["id"] not in url and "#/jobs/" in url)
    again = page.url.rsplit("/", 1)[-1]
    twin = api.get(f"/v1/jobs/{again}").json()
    assert twin["settings"] == job["settings"] and twin["scene"] == job["scene"]
    expect(page.locator("#job-state")).to_have_text("succeeded", timeout=JOB_TIMEOUT_MS)
    page.click("#delete-button")
    expect(page.locator("#list-view")).to_be_visible()
    assert api.get(f"/v1/jobs/{again}").status_code == 404
    expect(page.locator(f"#job-table tr[data-job='{again}']")).to_have_count(0)
    watched.check_clean()


def test_job_list_filters_sorts_and_pages(server, watched, api, tmp_path):
    from playwright.sync_api import expect

    held = HeldSlots(server.url, server.settings.max_concurrent_jobs)
    try:
        ids = [api.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()["id"]
               for _ in range(11)]
        for job_id in ids:
            api.post(f"/v1/jobs/{job_id}/cancel")
    finally:
        held.release()
    canceled = api.get("/v1/jobs", params={"state": "canceled", "limit": 500}).json()
    page = watched.page
    page.goto(server.url + "/")
    page.select_option("#state-filter", "canceled")
    page.select_option("#page-size", "10")
    rows = page.locator("#job-table tbody tr")
    expect(rows).to_have_count(10)
    expect(page.locator("#job-count")).to_have_text(f"({canceled['count']} canceled)")
    pages = -(-canceled["count"] // 10)
    expect(page.locator("#page-info")).to_have_text(f"page 1 of {pages}")
    expect(rows.first).to_have_attribute("data-job", canceled["data"][0]["id"])  # newest
    expect(rows.locator(".state")).to_have_text(["canceled"] * 10)
    expect(rows.first.locator(".settings")).to_have_text("32×32 · 4 spp · exact · reference")
    expect(rows.first.locator(".age")).to_contain_text("ago")
    page.click("#next-page")
    expect(page.locator("#page-info")).to_have_text(f"page 2 of {pages}")
    expect(rows).to_have_count(canceled["count"] - 10)
    page.select_option("#sort", "oldest")  # back to page 1, oldest first
    expect(rows.first).to_have_attribute("data-job", canceled["data"][-1]["id"])
    page.screenshot(path=str(tmp_path / "list.png"), full_page=True)
    page.select_option("#state-filter", "succeeded")
    expect(rows.locator(".state").first).to_have_text("succeeded")
    watched.check_clean()


def test_scene_upload_from_the_page_selects_the_new_scene(server, watched, tmp_path):
    from playwright.sync_api import expect

    glb = two_box_glb(tmp_path / "two_boxes.glb")
    page = watched.page
    page.goto(server.url + "/")
    page.set_input_files("#upload-file", str(glb))
    page.click("#upload-button")
    status = page.locator("#upload-status")
    expect(status).to_contain_text("uploaded two_boxes.glb as scene")
    expect(status).to_contain_text("2 instances of 1 meshes")
    scene_id = page.eval_on_selector("#scene-select", "s => s.value")
    assert len(scene_id) == 64  # the sha256 of the upload
    expect(page.locator("#size-label")).to_be_hidden()  # sizes are for demos only
    page.screenshot(path=str(tmp_path / "upload.png"), full_page=True)
    watched.check_clean()


def test_proxy_job_shards_phases_and_ab_view_against_exact(server, watched, api, tmp_path):
    from playwright.sync_api import expect

    exact = api.post("/v1/jobs", json={"scene": "forest:small", **SHARDED}).json()
    assert _done(api, exact["id"])["state"] == "succeeded"
    # An accuracy target forest:small's tree proxies meet (at the default the plan copies
    # the trees to every shard, and the proxy job would be the exact image).
    proxy = api.post("/v1/jobs", json={"scene": "forest:small", **SHARDED, "mode": "proxy",
                                       "proxy": {"band": 0.2, "accuracy_target": 0.9}}).json()
    page = watched.page
    page.goto(f"{server.url}/#/jobs/{proxy['id']}")
    expect(page.locator("#job-state")).to_have_text("succeeded", timeout=JOB_TIMEOUT_MS)
    expect(page.locator("#settings-table tr[data-key='proxy band'] td").nth(1)).to_have_text(
        "0.2 (shadow rays: 0)")
    expect(page.locator("#shard-table tbody tr")).to_have_count(2)
    expect(page.locator("#shard-table tbody tr").first.locator(".busy")).to_contain_text("%")
    # CPU seconds per shard and of the coordinator (Coordinator.info()).
    expect(page.locator("#shard-table thead")).to_contain_text("CPU")
    expect(page.locator("#shard-table tbody tr").first.locator(".cpu")).to_have_text(
        re.compile(r"\d"))
    expect(page.locator("#shard-panel")).to_contain_text("coordinator CPU")
    expect(page.locator("#stats-table")).to_contain_text("shard CPU total")
    expect(page.locator("#phase-caption")).to_contain_text("summed over the 2 shards, "
                                                           "divided by 2")
    expect(page.locator("#phase-svg rect[data-phase='wall time']")).to_have_count(1)
    expect(page.locator("#phase-chart li[data-phase=transfer_wait]")).to_contain_text(
        "not a share of the wall time")  # it overlaps itself: shown apart from the bars
    # Phase bars are per-shard means: none may be longer than the wall-time bar.
    widths = page.eval_on_selector_all("#phase-svg rect", "rs => rs.map(r => "
                                       "[r.dataset.phase, r.width.baseVal.value])")
    wall = dict(widths)["wall time"]
    assert all(w <= wall + 1e-6 for _, w in widths), widths
    expect(page.locator("#stats-table")).to_contain_text("bytes saved vs exact")

    body = page.locator("#compare-body")
    expect(body).to_be_visible(timeout=20_000)
    expect(page.locator("#compare-what")).to_contain_text(exact["id"][:8])
    expect(page.locator("#compare-stats tr[data-key=RMSE]")).to_have_count(1)
    page.locator("#compare-slider").fill("20")
    clip = page.eval_on_selector("#compare-b", "c => c.style.clipPath")
    assert clip == "inset(0px 80% 0px 0px)", clip
    page.screenshot(path=str(tmp_path / "ab-slider.png"), full_page=True)
    page.check("input[name=compare-mode][value=flicker]")
    label = page.locator("#flicker-label")
    expect(label).to_have_text("A: exact")
    expect(label).to_have_text("B: proxy")
    page.check("input[name=compare-mode][value=error]")
    expect(page.locator("#error-map")).to_be_visible()
    expect(page.locator("#compare-stage")).to_be_hidden()
    assert _canvas_mean(page, "#error-map") > 0.0  # proxy pixels differ from exact ones
    page.screenshot(path=str(tmp_path / "ab-error-map.png"), full_page=True)
    watched.check_clean()


def test_frames_job_page_has_a_frame_selector_showing_each_frame(server, watched, api,
                                                                 tmp_path):
    from playwright.sync_api import expect

    page = watched.page  # submitted from the form, with its frame range
    page.goto(server.url + "/")
    expect(page.locator("#scene-select option[value=windy]")).to_have_count(1)
    page.select_option("#scene-select", "windy")
    page.select_option("select[name=size]", "tiny")
    for name, value in {**TINY, "frame_first": 1, "frame_last": 3}.items():
        page.fill(f"input[name={name}]", str(value))
    page.click("#submit-button")
    expect(page.locator("#job-view")).to_be_visible()
    job_id = page.evaluate("location.hash").rsplit("/", 1)[-1]
    job = _done(api, job_id)
    assert job["state"] == "succeeded", job["error"]
    assert job["frames"] == {"first": 1, "last": 3}
    page.goto(f"{server.url}/#/jobs/{job['id']}")
    expect(page.locator("#frame-panel")).to_be_visible()
    expect(page.locator("#frame-select option")).to_have_text(["1", "2", "3"])
    shown = {}
    for f in ("1", "3"):
        page.select_option("#frame-select", f)
        expect(page.locator("#frame-png-link")).to_have_attribute(
            "href", f"/v1/jobs/{job['id']}/frames/{f}.png")
        expect(page.locator("#frame-image")).to_be_visible()
        page.wait_for_function("document.querySelector('#frame-image').naturalWidth == 32")
        shown[f] = page.locator("#frame-image").screenshot()
    page.screenshot(path=str(tmp_path / "frames.png"), full_page=True)
    assert shown["1"] != shown["3"]  # another frame, another picture
    assert not watched.errors and not watched.bad, (watched.errors, watched.bad)
    plain = _done(api, api.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()["id"])
    page.goto(f"{server.url}/#/jobs/{plain['id']}")
    expect(page.locator("#job-state")).to_have_text("succeeded")
    expect(page.locator("#frame-panel")).to_be_hidden()
