"""Real browser tests: uvicorn in a thread, Debian chromium through Playwright.

Screenshots go to ``docs/screenshots/`` when ``LAYERWATCH_SCREENSHOTS=1``,
otherwise to the test's temporary folder.
"""

from __future__ import annotations

import pytest

from browser_stack import BROWSER_MARKS, launch, screenshot_dir, serve

pytestmark = [*BROWSER_MARKS, pytest.mark.xdist_group("servers")]


@pytest.fixture
def server(seeded, printer):
    from layerwatch.web.app import create_app

    h, root, ids = seeded
    app = create_app(h, printers={"virtual": printer}, image_root=root, poll_s=0.2)
    with serve(app, "/api/jobs") as url:
        yield url, ids, h


@pytest.fixture
def shots(tmp_path):
    return screenshot_dir(tmp_path)


@pytest.mark.slow
def test_dashboard_buttons_and_screenshots(server, printer, shots):
    sync_api = pytest.importorskip("playwright.sync_api")
    # the event log updates over SSE (1 s poll); a loaded CI machine needs more than the 5 s default
    sync_api.expect.set_options(timeout=20_000)
    url, ids, h = server
    with sync_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 1100})
            page.goto(url + "/")
            page.wait_for_selector("body[data-ready='1']")
            page.wait_for_selector("#curve polyline")
            page.wait_for_selector("#threshold-line", state="attached")
            assert "first failing layer" in page.inner_text("#job-meta")
            for sel in ("#img-top", "#img-reference", "#img-overlay", "#img-stack"):
                # a function, not an expression string: Playwright evals strings, which the page's CSP forbids
                page.wait_for_function(f"() => document.querySelector('{sel}').naturalWidth > 0")
            state = page.locator(".printer .state")
            assert state.inner_text() == "printing"

            page.click("button[data-action='pause']")
            sync_api.expect(state).to_have_text("paused")
            assert printer.status().state == "paused"
            page.click("button[data-action='acknowledge']")
            sync_api.expect(page.locator("#events")).to_contain_text("acknowledge requested")
            page.click("button[data-action='resume']")
            sync_api.expect(state).to_have_text("printing")
            assert printer.status().state == "printing"
            kinds = [e["kind"] for e in h.events(ids["live"])]
            assert kinds[-3:] == ["pause", "acknowledge", "resume"]
            page.click("#ack-job")  # the live job's own button: the monitor of that job reads it
            sync_api.expect(page.locator("#ack-msg")).to_have_text("acknowledged")
            assert h.events(ids["live"])[-1]["kind"] == "acknowledge"
            page.wait_for_timeout(300)
            page.screenshot(path=str(shots / "dashboard-desktop.png"), full_page=True)

            phone = browser.new_page(viewport={"width": 390, "height": 844}, device_scale_factor=2, is_mobile=True)
            phone.goto(url + "/")
            phone.wait_for_selector("body[data-ready='1']")
            phone.wait_for_function("() => document.querySelector('#img-overlay').naturalWidth > 0")
            width = phone.evaluate("document.documentElement.scrollWidth")
            assert width <= 390, "the page must not scroll sideways on a phone"
            phone.screenshot(path=str(shots / "dashboard-phone.png"), full_page=True)

            linked = browser.new_page()
            linked.goto(url + f"/#job={ids['done']}")  # a link to a past job opens that job
            linked.wait_for_selector("#curve polyline")
            sync_api.expect(linked.locator("#job-title")).to_contain_text(f"Job #{ids['done']}")
            assert linked.locator("#ack-job").is_hidden()  # an ended job has nothing to acknowledge
        finally:
            browser.close()


@pytest.mark.slow
def test_settings_validated_in_browser(server):
    sync_api = pytest.importorskip("playwright.sync_api")
    url, _, _ = server
    with sync_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            page = browser.new_page()
            page.goto(url + "/")
            page.wait_for_selector("body[data-ready='1']")
            page.fill("#set-pause", "0.2")
            page.select_option("#set-metric", "pearson")
            page.click("#settings button[type='submit']")
            sync_api.expect(page.locator("#settings-msg")).to_have_text("saved")
            page.evaluate("document.querySelector('#set-threshold').removeAttribute('max')")
            page.fill("#set-threshold", "5")
            page.click("#settings button[type='submit']")
            sync_api.expect(page.locator("#settings-msg")).to_contain_text("invalid")
        finally:
            browser.close()


@pytest.mark.slow
def test_report_renders_in_browser(seeded, shots, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    from layerwatch.web.report import build_report

    h, _, ids = seeded
    path = build_report(h, ids["live"], tmp_path / "report")
    with sync_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            page = browser.new_page(viewport={"width": 1000, "height": 900})
            page.goto(path.as_uri())
            n = page.evaluate("[...document.images].filter(i => i.complete && i.naturalWidth > 0).length")
            assert n == page.evaluate("document.images.length") >= 5
            page.screenshot(path=str(shots / "report.png"), full_page=True)
        finally:
            browser.close()


ATTACK = """<!doctype html><html><body>
<form id="f" method="post" action="{url}/api/printers/virtual/pause"></form>
<script>
  fetch("{url}/api/printers/virtual/cancel", {{method: "POST", mode: "no-cors", credentials: "include"}});
  fetch("{url}/api/settings", {{method: "PATCH", mode: "no-cors", credentials: "include",
        headers: {{"content-type": "text/plain"}}, body: '{{"policy": {{"pause_ratio": 0.5}}}}'}});
  setTimeout(() => document.getElementById("f").submit(), 300);
</script></body></html>"""


@pytest.mark.slow
def test_cross_site_page_cannot_press_the_buttons(server, printer):
    """A page on another site, open in the same browser as the dashboard, posts to it: nothing changes."""
    sync_api = pytest.importorskip("playwright.sync_api")
    url, ids, h = server
    with sync_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            ctx = browser.new_context()
            dash = ctx.new_page()
            dash.goto(url + "/")  # the victim has the dashboard open: its session cookie is in the browser
            dash.wait_for_selector("body[data-ready='1']")
            evil = ctx.new_page()
            evil.route("http://attacker.test/**", lambda route: route.fulfill(
                status=200, content_type="text/html", body=ATTACK.format(url=url)))
            with evil.expect_navigation(url=f"{url}/api/printers/virtual/pause"):
                evil.goto("http://attacker.test/")
            assert "refused" in evil.content()
            assert printer.status().state == "printing"
            assert h.audit() == [] and h.setting("job_config") is None
        finally:
            browser.close()


@pytest.mark.slow
def test_pause_switch_and_audit_log_in_browser(server, printer):
    sync_api = pytest.importorskip("playwright.sync_api")
    sync_api.expect.set_options(timeout=20_000)
    url, _, h = server
    with sync_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            page = browser.new_page()
            page.on("dialog", lambda d: d.accept())
            page.goto(url + "/")
            page.wait_for_selector("body[data-ready='1']")
            assert page.is_checked("#pausing") and page.locator("#pausing-off").is_hidden()
            page.click("#pausing")
            sync_api.expect(page.locator("#pausing-off")).to_be_visible()
            assert h.setting("job_config")["policy"]["action"] == "notify"
            page.click("button[data-action='pause']")
            sync_api.expect(page.locator("#audit")).to_contain_text("pause printer virtual")
            sync_api.expect(page.locator("#audit")).to_contain_text("pausing off")
            assert [a["action"] for a in h.audit()] == ["pause", "pausing off"]
            page.click("#pausing")
            sync_api.expect(page.locator("#pausing-off")).to_be_hidden()
        finally:
            browser.close()
