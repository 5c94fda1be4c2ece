"""Back-pressure (bounded lanes that drop the oldest frame, recorded) and late verdicts that never pause."""

from __future__ import annotations

import threading
import time
from concurrent.futures import Executor

import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult
from layerwatch.farm.monitor import FarmMonitor
from layerwatch.farm.pool import FrameLane
from layerwatch.monitor.printers.base import SnapshotTrigger
from layerwatch.monitor.printers.virtual import VirtualPrinter
from layerwatch.pipeline.policy import Decision
from layerwatch.storage.history import History


def test_lane_keeps_the_newest_frames_and_reports_each_drop():
    gate, ran, dropped = threading.Event(), [], []
    lane = FrameLane(2, on_drop=dropped.append)

    def work(i):
        if i == 0:
            gate.wait(10)
        ran.append(i)
        return i

    futs = [lane.submit(work, 0)]
    time.sleep(0.05)  # frame 0 is running
    futs += [lane.submit(work, i) for i in range(1, 6)]
    assert lane.pending == 2 and lane.dropped == 3
    assert dropped == [(1,), (2,), (3,)]
    gate.set()
    lane.shutdown(wait=True)
    assert ran == [0, 4, 5]  # in order, the newest kept
    assert [f.cancelled() for f in futs] == [False, True, True, True, False, False]
    with pytest.raises(RuntimeError):
        lane.submit(work, 9)


class _Camera:
    def grab(self):
        return np.zeros((32, 32, 3), np.uint8)


class _GatedPipeline:
    """Processing waits for ``gate``; every result is 'ok'."""

    def __init__(self):
        self.gate = threading.Event()
        self.started = threading.Event()

    def process(self, photo, layer):
        self.started.set()
        assert self.gate.wait(10)
        return LayerResult(layer=layer, z=0.2 * (layer + 1), status="ok", anomaly_ratio=0.5)


class _AlwaysPause:
    """A policy that asks for a pause on every layer (the decision under test is the monitor's, not the policy's)."""

    halted = False
    acknowledged: list = []

    def update(self, res):
        return Decision("pause", f"layer {res.layer}: failure", res.layer)

    def acknowledge(self):
        pass


def _monitor(tmp_path, queue_frames=2):
    h = History(tmp_path / "h.db")
    job = h.start_job("p01")
    printer = VirtualPrinter(b"G1 Z0.2\n", name="t.gcode")
    pipe = _GatedPipeline()
    mon = FarmMonitor(printer, _Camera(), pipe, _AlwaysPause(), history=h, job_id=job, queue_frames=queue_frames)
    return mon, printer, pipe, h, job


def test_saturated_printer_drops_oldest_frames_with_events(tmp_path):
    mon, printer, pipe, h, job = _monitor(tmp_path, queue_frames=2)
    printer.pause = lambda: None  # keep every layer judged the same way
    for layer in range(6):
        mon.handle_trigger(SnapshotTrigger(layer, 0.2))
        if layer == 0:
            assert pipe.started.wait(5)
        assert mon._pool.pending <= 2  # never queued without bound
    pipe.gate.set()
    mon.close()
    analysed = [r.layer for r in mon.report.results]
    drops = [e["data"]["layer"] for e in h.events(job) if e["kind"] == "frame_dropped"]
    assert analysed == [0, 4, 5] and drops == [1, 2, 3] and mon.dropped == 3
    h.close()


@pytest.mark.parametrize("operator_acted", [False, True])
def test_late_verdict_never_pauses_after_the_operator_acted(tmp_path, operator_acted):
    mon, printer, pipe, h, job = _monitor(tmp_path)
    mon.handle_trigger(SnapshotTrigger(5, 1.2))  # photo of layer 5, analysed slowly
    assert pipe.started.wait(5)
    if operator_acted:
        mon.acknowledge("dashboard")  # the operator looked at the print after that photo
    pipe.gate.set()
    mon.close()
    kinds = [e["kind"] for e in h.events(job)]
    if operator_acted:
        assert printer.status().state == "printing" and printer.pause_count == 0
        assert "late_verdict" in kinds and "pause" not in kinds
        assert mon.report.results[0].decision == "none" and mon.late == 1
        assert [r.layer for r in h.layers(job)] == [5]  # the record is kept
    else:  # the same verdict in time pauses (the test can fail)
        assert printer.status().state == "paused" and "pause" in kinds and mon.late == 0
    h.close()


def test_verdict_of_an_ended_job_never_pauses(tmp_path):
    mon, printer, pipe, h, job = _monitor(tmp_path)
    mon.handle_trigger(SnapshotTrigger(3, 0.8))
    assert pipe.started.wait(5)
    mon.new_generation("job ended")
    pipe.gate.set()
    mon.close()
    assert printer.pause_count == 0 and mon.late == 1
    h.close()


def test_lane_is_an_executor_with_keyword_arguments_and_cancel_futures():
    gate = threading.Event()
    lane = FrameLane(3)
    assert isinstance(lane, Executor)
    first = lane.submit(lambda: gate.wait(10))
    time.sleep(0.05)  # the first call is running
    kw = lane.submit(lambda a, *, b: a + b, 1, b=2)
    later = lane.submit(lambda: "never")
    lane.shutdown(wait=False, cancel_futures=True)
    assert kw.cancelled() and later.cancelled() and lane.pending == 0
    gate.set()
    assert first.result(timeout=10) is True
    lane2 = FrameLane(1)
    assert lane2.submit(lambda a, *, b: a + b, 1, b=2).result(timeout=10) == 3
    lane2.shutdown()


def test_fair_slots_hand_a_freed_slot_to_the_longest_waiter():
    """A thread that frees a slot and asks again at once waits behind those that asked before (a semaphore would
    let it barge in: under saturation a printer whose verdict just came would starve the others)."""
    from layerwatch.farm.pool import FairSlots

    slots, order, lock = FairSlots(1), [], threading.Lock()
    slots.acquire()

    def waiter(name):
        with slots:
            with lock:
                order.append(name)

    threads = [threading.Thread(target=waiter, args=(n,)) for n in ("a", "b")]
    for i, t in enumerate(threads):
        t.start()
        deadline = time.monotonic() + 10
        while len(slots._waiters) < i + 1 and time.monotonic() < deadline:  # it waits for the slot
            time.sleep(0.001)
    slots.release()
    slots.acquire()  # asked again at once: after "a" and "b"
    order.append("me")
    slots.release()
    for t in threads:
        t.join(5)
    assert order == ["a", "b", "me"]
