"""The farm view in Debian chromium: 20 virtual printers, one injected failure pauses exactly that printer.

Screenshots go to ``docs/screenshots/`` when ``LAYERWATCH_SCREENSHOTS=1``,
otherwise to the test's temporary folder.
"""

from __future__ import annotations

import pytest

from browser_stack import BROWSER_MARKS, launch, screenshot_dir, serve
from layerwatch.farm import Farm, parse_farm
from layerwatch.storage.history import History

#: exclusive: 20 printers at 2 s a layer must be analysed as they print (tests/xdist_groups.py)
pytestmark = [*BROWSER_MARKS, pytest.mark.slow, pytest.mark.xdist_group("servers"), pytest.mark.exclusive]
FAILING = "p07"


@pytest.fixture
def farm_server(tmp_path):
    from layerwatch.web.app import create_app

    printers = [{"name": f"p{i:02d}", "layer_seconds": 2.0} for i in range(1, 21)]
    printers[6].update(failure="spaghetti", onset=8)
    assert printers[6]["name"] == FAILING
    h = History(tmp_path / "h.db")
    farm = Farm(parse_farm({"farm": {"workers": 2, "queue_frames": 2}, "printers": printers}, tmp_path), h)
    app = create_app(h, printers=farm.printers, poll_s=0.5)
    with serve(app, "/api/printers") as url:
        farm.start()
        try:
            yield url, farm, h
        finally:
            farm.stop()
    h.close()


@pytest.fixture
def shots(tmp_path):
    return screenshot_dir(tmp_path)


def test_twenty_printers_one_failure_pauses_exactly_that_one(farm_server, shots):
    sync_api = pytest.importorskip("playwright.sync_api")
    sync_api.expect.set_options(timeout=150_000)
    url, farm, h = farm_server
    with sync_api.sync_playwright() as pw:
        browser = launch(pw)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1250})
            page.goto(url + "/farm")
            page.wait_for_selector("body[data-ready='1']")
            sync_api.expect(page.locator(".farm-card")).to_have_count(20)
            failing = page.locator(f".farm-card[data-printer='{FAILING}']")
            sync_api.expect(failing.locator("[data-testid=state]")).to_have_text("paused")  # live: no reload
            sync_api.expect(failing.locator("[data-testid=alarm]")).to_contain_text("pause")
            cards = {c["name"]: c for c in farm.summaries()}
            others = [n for n in cards if n != FAILING]
            assert all(cards[n]["state"] == "printing" for n in others), {n: cards[n]["state"] for n in others}
            assert all(farm.stations[n].printer.pause_count == 0 for n in others)
            assert farm.stations[FAILING].printer.pause_count == 1
            # the other 19 keep printing: their layers advance after the pause
            before = {n: cards[n]["layer"] for n in others}
            after: dict = {}
            for _ in range(120):  # a layer each 2 s; a loaded machine analyses late, so wait up to 60 s
                page.wait_for_timeout(500)
                after = {c["name"]: c for c in farm.summaries()}
                if all((after[n]["layer"] or -1) > (before[n] or -1) for n in others):
                    break
            assert all((after[n]["layer"] or -1) > (before[n] or -1) for n in others), (
                before, {n: after[n]["layer"] for n in others})
            assert farm.stations[FAILING].printer.pause_count == 1 and all(
                farm.stations[n].printer.pause_count == 0 for n in others)
            for n in (FAILING, "p01"):  # overlay thumbnails arrive
                page.wait_for_function(
                    "(n) => { const i = document.querySelector(`.farm-card[data-printer='${n}'] img.thumb`);"
                    " return i && i.naturalWidth > 0; }", arg=n)
            assert page.locator(".farm-card.state-paused").count() == 1
            page.screenshot(path=str(shots / "farm-20-printers-one-paused.png"), full_page=True)
            # buttons: resume the paused printer (CSRF header from the page, audit-logged)
            failing.locator("button[data-action='resume']").click()
            sync_api.expect(failing.locator("[data-testid=state]")).to_have_text("printing")
            assert any(a["action"] == "resume" and a["target"] == f"printer {FAILING}" for a in h.audit())
            failing.locator("button[data-action='acknowledge']").click()
            page.wait_for_function("() => true")
            # click-through to the printer's job page (the card's link, whatever job it shows when clicked: a
            # resumed virtual printer may finish its job and start the next one while the page re-renders)
            jobs_before = {farm.summaries()[6]["job_id"]}
            failing.locator("[data-testid=job]").click()
            page.wait_for_url("**/#job=*")
            job_id = page.url.rsplit("#job=", 1)[1]
            assert int(job_id) in jobs_before | {farm.summaries()[6]["job_id"]}, (job_id, jobs_before)
            page.wait_for_selector("body[data-ready='1']")
            sync_api.expect(page.locator("#job-select")).to_have_value(job_id)
        finally:
            browser.close()
