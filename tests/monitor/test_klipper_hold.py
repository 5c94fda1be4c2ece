"""The Klipper hold handshake through a REAL Moonraker and Klippy: the host's acknowledgement gets in
between the prepared file's LAYERWATCH_WAIT lines and ends the hold; with no host the hold runs out.

Klippy runs in debug-output mode (see moonraker_stack.py), where G4 dwells take no real time, so the
photo window is made real with the test-support ``LAYERWATCH_TEST_LAYER_TIME``; what is checked is
the macros' own state (``taken``, ``misses``) as Klippy reports it, which only reads 0 misses if
every layer's acknowledgement was seen by that layer's LAYERWATCH_WAIT steps.
"""

import re
import threading
import time

import httpx
import pytest
from moonraker_stack import MoonrakerStack, require_installed, running, until

from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.printers.moonraker import MoonrakerPrinter

pytestmark = [pytest.mark.moonraker, pytest.mark.xdist_group("servers")]

N_LAYERS, STEPS = 5, 4


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    require_installed()
    s = MoonrakerStack(tmp_path_factory.mktemp("klipper_hold"))
    with running(s):
        yield s


def hold_gcode() -> str:
    lines = ["G90"]
    for i in range(N_LAYERS):
        lines += [f"LAYERWATCH_SNAPSHOT LAYER={i} Z={0.2 * (i + 1):.3f}", "LAYERWATCH_TEST_LAYER_TIME SECONDS=0.6"]
        lines += [f"LAYERWATCH_WAIT LAYER={i} STEP={k} OF={STEPS}" for k in range(STEPS)]
    return "\n".join(lines) + "\n"


def macro_state(stack) -> dict:
    return stack.query("gcode_macro LAYERWATCH_SNAPSHOT")["gcode_macro LAYERWATCH_SNAPSHOT"]


def print_and_wait(stack, name: str, host: bool) -> list[int]:
    """Print ``hold_gcode()``; when ``host``, acknowledge every announced layer like layerwatch would."""
    acked: list[int] = []
    done = threading.Event()

    client = MoonrakerPrinter(stack.url, push=False)  # the monitor's own connector ends each hold

    def host_loop():
        while not done.is_set():
            store = httpx.get(stack.url + "/server/gcode_store", params={"count": 100}, timeout=5).json()
            for item in store["result"]["gcode_store"]:
                m = re.search(r"layerwatch snapshot layer=(\d+)", item["message"])
                if m and int(m.group(1)) not in acked and item["time"] > started:
                    acked.append(int(m.group(1)))
                    client.photo_done(SnapshotTrigger(acked[-1], 0.0, "moonraker"))  # what the monitor sends
            time.sleep(0.05)

    started = time.time()
    thread = threading.Thread(target=host_loop, daemon=True)
    if host:
        thread.start()
    stack.upload_and_print(name, hold_gcode())
    until(lambda: stack.query("print_stats")["print_stats"]["state"] == "printing", 20, "printing")
    until(lambda: stack.query("print_stats")["print_stats"]["state"] == "complete", 60, "print complete")
    done.set()
    if host:
        thread.join(10)
    client.close()
    return acked


@pytest.mark.slow
def test_dead_host_runs_the_hold_out_and_a_live_host_ends_it(stack):
    print_and_wait(stack, "no_host.gcode", host=False)
    st = macro_state(stack)
    assert st["taken"] == -1 and st["misses"] == 3  # layers 0-2 missed, then capped

    acked = print_and_wait(stack, "host.gcode", host=True)
    st = macro_state(stack)
    assert acked == list(range(N_LAYERS))
    assert st["taken"] == N_LAYERS - 1 and st["misses"] == 0
