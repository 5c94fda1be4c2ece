"""Integration test against a REAL OctoPrint (1.11) with its virtual printer."""

import time

import httpx
import pytest

from layerwatch.errors import PrinterError
from layerwatch.gcode.objects import PrintObject
from layerwatch.monitor.printers.octoprint import OctoPrintPrinter, parse_octoprint_message
from layerwatch.pipeline.actions import ActionExecutor
from layerwatch.pipeline.policy import Decision
from layerwatch.storage.history import History
from octoprint_stack import OCTO, VENV, octoprint_server, until

pytestmark = pytest.mark.xdist_group("servers")


def test_parse_recorded_push_message():
    msg = {"current": {"logs": ["Send: N12 M118 E1 layerwatch snapshot layer=3 z=1.200*77",
                                "Recv: echo:layerwatch snapshot layer=3 z=1.200", "Recv: ok"]}}
    (t,) = parse_octoprint_message(msg)
    assert (t.layer, t.z, t.source) == (3, 1.2, "octoprint")
    assert parse_octoprint_message({"event": {"type": "PrintStarted"}}) == []
    # the replay of past serial lines that opens every connection is no trigger: those moments are gone
    assert parse_octoprint_message({"history": msg["current"]}) == []


@pytest.fixture(scope="session")
def octoprint(tmp_path_factory):
    if not OCTO.exists():
        pytest.skip(f"OctoPrint not installed at {VENV}; run .ci/install-octoprint")
    with octoprint_server(tmp_path_factory.mktemp("octoprint")) as served:
        yield served


def _gcode(n_layers=6):
    lines = ["G28", "G90", "M83"]
    for i in range(n_layers):
        z = 0.3 * (i + 1)
        lines += [f"G1 Z{z:.2f} F600"]
        lines += [f"G1 X{60 + 10 * (k % 2)} Y{60 + k} E0.1 F1200" for k in range(20)]
        msg = f"layerwatch snapshot layer={i} z={z:.3f}"
        lines += ["M400", f"@{msg}", f"M118 E1 {msg}", "G4 P200"]
    return ("\n".join(lines) + "\n").encode()


@pytest.mark.slow
@pytest.mark.octoprint
def test_real_octoprint_triggers_and_pause(octoprint):
    url, key = octoprint
    h = {"X-Api-Key": key}
    with OctoPrintPrinter(url + "?key=WRONG", push=False) as bad, pytest.raises(PrinterError, match="refused the API key"):
        bad.status()
    httpx.post(url + "/api/connection", headers=h, json={"command": "connect", "port": "VIRTUAL", "baudrate": 115200,
                                                          "autoconnect": False}, timeout=10).raise_for_status()
    until(lambda: httpx.get(url + "/api/connection", headers=h, timeout=2).json()["current"]["state"] == "Operational",
           30, "virtual printer connection")
    printer = OctoPrintPrinter(f"octoprint://{url[7:]}?key={key}")
    try:
        assert printer.wait_connected(15)
        r = httpx.post(url + "/api/files/local", headers=h, files={"file": ("lw.gcode", _gcode(40), "application/octet-stream")},
                       data={"select": "true", "print": "true"}, timeout=10)
        r.raise_for_status()
        seen = []
        until(lambda: seen.extend(printer.poll_triggers()) or len(seen) >= 2, 40, "two layer triggers")
        assert [t.layer for t in seen[:2]] == [0, 1]
        t0 = seen[1].time
        # a connection opened now is replayed those triggers (OctoPrint's `history` message): never as triggers
        with OctoPrintPrinter(f"octoprint://{url[7:]}?key={key}") as late:
            assert late.wait_connected(15)
            time.sleep(1.0)
            assert [t.layer for t in late.poll_triggers() if t.layer <= 1] == []  # later ones may be live
        printer.pause()
        print(f"\nOctoPrint: trigger -> pause request {1000 * (time.monotonic() - t0):.0f} ms (no analysis)")
        states = []
        until(lambda: states.append(printer.status().state) or states[-1] == "paused", 20, "job state Paused")
        assert set(states) <= {"printing", "pausing", "paused"}, states
        # "paused" now means OctoPrint's exact "Paused" ("Pausing" is its own state; a resume then is ignored)
        assert httpx.get(url + "/api/job", headers=h, timeout=2).json()["state"] == "Paused"
        printer.resume()
        until(lambda: printer.status().state == "printing", 20, "job state Printing after resume")
        assert httpx.get(url + "/api/job", headers=h, timeout=2).json()["state"] == "Printing"
        printer.cancel()
    finally:
        printer.close()


@pytest.mark.slow
@pytest.mark.octoprint
def test_real_octoprint_shows_the_reason_and_takes_m486_object_cancels(octoprint, tmp_path):
    """The pause reason reaches OctoPrint's own API (the bundled action-command notification plugin,
    fed by the firmware's echo of ``M118 A1 action:notification``); an object cancel goes out as
    ``M486 P<id>`` through the command API (OctoPrint has no object-cancel API of its own)."""
    url, key = octoprint
    h = {"X-Api-Key": key}
    httpx.post(url + "/api/connection", headers=h, json={"command": "connect", "port": "VIRTUAL", "baudrate": 115200,
                                                          "autoconnect": False}, timeout=10).raise_for_status()
    until(lambda: httpx.get(url + "/api/connection", headers=h, timeout=2).json()["current"]["state"] == "Operational",
           30, "virtual printer connection")
    httpx.post(url + "/api/plugin/action_command_notification", headers=h, json={"command": "clear"}, timeout=5)
    printer = OctoPrintPrinter(f"octoprint://{url[7:]}?key={key}")
    hist = History(tmp_path / "h.db")
    try:
        r = httpx.post(url + "/api/files/local", headers=h, files={"file": ("lw2.gcode", _gcode(40), "application/octet-stream")},
                       data={"select": "true", "print": "true"}, timeout=10)
        r.raise_for_status()
        until(lambda: printer.status().state == "printing", 20, "printing")
        ex = ActionExecutor(printer, history=hist, job_id=1)
        obj = PrintObject(1, "cube_1 id:0 copy 0", 1, None, (0.0, 0.0, 5.0, 5.0))
        printer.cancel_object(obj)  # M486 P1: accepted by OctoPrint and sent to the firmware
        done = ex.execute(Decision("pause", "layer 3: anomaly ratio 30% above 2.5% for 2 layers", 3, "spaghetti"))
        assert done.ok
        until(lambda: printer.status().state == "paused", 20, "job state Paused")

        def notes():
            got = httpx.get(url + "/api/plugin/action_command_notification", headers=h, timeout=5).json()
            return [n["message"] for n in got["notifications"]]
        until(lambda: "layerwatch: pause L3 spaghetti" in notes(), 20, "the reason in OctoPrint's notifications")
        (row,) = hist.audit()
        assert (row["action"], row["actor"], row["detail"]["kind"]) == ("pause", "layerwatch", "spaghetti")
        no_labels = PrintObject(0, "part", None, None, (0.0, 0.0, 5.0, 5.0))
        with pytest.raises(PrinterError, match="no M486 labels"):
            printer.cancel_object(no_labels)
        printer.cancel()
    finally:
        hist.close()
        printer.close()
