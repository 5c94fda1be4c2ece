"""A farm printer without ``gcode`` picks up each job its host starts (the monitor's JobWatcher), through the
image store and park check of ``layerwatch monitor --follow``."""

from __future__ import annotations

import time

import httpx
import pytest

from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.farm import Farm, parse_farm
from layerwatch.farm import station as station_module
from layerwatch.farm.virtual import PacedVirtualPrinter
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.monitor.hosts import OctoPrintJobs
from layerwatch.pipeline.config import load_config
from layerwatch.storage.history import History

#: exclusive: the paced printer (0.4 s a layer) does not wait for the analyses (tests/xdist_groups.py)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("servers"), pytest.mark.exclusive]


@pytest.mark.parametrize("head", ["unknown", "off the park spot"])
def test_followed_printer_picks_up_a_prepared_job_and_refuses_an_unprepared_one(tmp_path, monkeypatch, head):
    cfg = load_config(PART_CONFIG)
    ready = insert_snapshots(PART_GCODE.read_bytes(), cfg.snapshot.model_copy(update={"profile": "octoprint"}), cfg.printer)
    # the host: prints prepared.gcode until the printer finished it, then plain.gcode (no triggers)
    printer = PacedVirtualPrinter(ready, 0.4, name="prepared.gcode")
    phase = {"job": "prepared.gcode"}

    def handler(request):
        if request.url.path.startswith("/downloads/"):
            body = ready if "prepared" in request.url.path else PART_GCODE.read_bytes()
            return httpx.Response(200, content=body, headers={"content-type": "text/plain"})
        if phase["job"] == "prepared.gcode" and printer.status().state == "finished":
            phase["job"] = "plain.gcode"
        return httpx.Response(200, json={"state": "Printing", "job": {"file": {"path": phase["job"], "origin": "local"}}})

    host = OctoPrintJobs(httpx.Client(base_url="http://printer.invalid", transport=httpx.MockTransport(handler)))
    monkeypatch.setattr(station_module, "job_host", lambda p: host)
    monkeypatch.setattr(station_module.Station, "_printer", lambda self, played, name: (printer.start(), printer)[1])
    asked = []  # the park check asks OctoPrint for M114 after each frame: unknown (no reply), or far from the spot
    where = None if head == "unknown" else (0.0, 0.0, 0.0)
    monkeypatch.setattr(station_module, "M114Position", lambda p: lambda: (asked.append(p), where)[1])
    h = History(tmp_path / "h.db")
    farm = Farm(parse_farm({"printers": [{"name": "mk4", "printer": "octoprint://printer.invalid:80?key=K"}]},
                           tmp_path), h, retry_s=(0.2, 1.0))
    with farm:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120:
            card = farm.summaries()[0]
            if "not analysed" in (card["message"] or ""):
                break
            time.sleep(0.2)
    rows = h.jobs()
    assert card["job"] == "plain.gcode" and "layerwatch gcode prepare" in card["message"], card
    analysed = [j for j in rows if j["n_layers"]]
    assert len(analysed) == 1 and analysed[0]["printer"] == "mk4", rows
    # the replay starts before the watcher sees the job (a real host too), so its first layer may be missed; on a
    # loaded machine the lane drops frames (each with an event), and the printer, which does not wait for the
    # photos, may end the job before the last triggers are taken: most layers are accounted for
    dropped = sum(e["kind"] == "frame_dropped" for e in h.events(analysed[0]["id"]))
    assert analysed[0]["n_layers"] >= 3 and analysed[0]["n_layers"] + dropped >= 24, (analysed, dropped)
    assert analysed[0]["gcode_path"] == "prepared.gcode"
    assert analysed[0]["outcome"] == "done"
    assert any(j["outcome"] == "not analysed" for j in rows)
    layers = h.layers(analysed[0]["id"])
    assert asked and all(p is printer for p in asked)
    images = tmp_path / "jobs" / f"{analysed[0]['id']:06d}"
    if head == "unknown":  # analysed, each layer's images in the store beside the history database
        assert all(r.status == "ok" for r in layers)
        assert all((tmp_path / r.images["overlay"]).is_file() and (tmp_path / r.images["top"]).is_file()
                   for r in layers), layers[0].images
        assert (images / "stack.png").is_file() and len(list((images / "refs").glob("*.png"))) == len(layers)
    else:  # every frame rejected by the park check: recorded, never analysed, never a pause
        assert all(r.status == "camera_fault" and "frame rejected: the head was at X0.00 Y0.00 Z0.00" in r.message
                   for r in layers), layers[0]
        assert not list(images.glob("tops/*.png"))
    h.close()
