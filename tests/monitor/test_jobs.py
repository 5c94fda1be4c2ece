"""Job pick-up pieces without a printer host: trigger check, park spots, park check, reply validation, retention.

The hosts themselves (real OctoPrint, real Moonraker + Klippy) are in test_jobs_real.py.
"""

import httpx
import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult
from layerwatch.errors import ConfigError, PrinterError
from layerwatch.examples import PART_CONFIG, PART_GCODE
from layerwatch.gcode import read_toolpath
from layerwatch.gcode.postprocess import insert_snapshots
from layerwatch.monitor.artifacts import ArtifactStore
from layerwatch.monitor.hosts import MoonrakerJobs, OctoPrintJobs, PrintJob
from layerwatch.monitor.jobs import JobNotPrepared, JobWatcher, check_prepared, find_triggers
from layerwatch.monitor.parked import FrameNotParked, ParkCheck, ParkedCamera, park_spots
from layerwatch.pipeline.config import load_config

PARK = (200.0, 200.0)


def prepared(profile: str) -> bytes:
    """The bundled example part prepared with ``profile``, parked at PARK."""
    cfg = load_config(PART_CONFIG)
    snap = cfg.snapshot.model_copy(update={"profile": profile, "park_xy_mm": PARK})
    return insert_snapshots(PART_GCODE.read_bytes(), snap, cfg.printer)


def test_prepared_files_carry_a_trigger_each_host_sees():
    n_layers = read_toolpath(PART_GCODE).n_layers
    assert check_prepared(prepared("octoprint"), "octoprint", "part.gcode") == n_layers  # the M118 lines
    assert check_prepared(prepared("klipper"), "moonraker", "part.gcode") == n_layers
    assert check_prepared(prepared("m240"), "octoprint", "part.gcode") == n_layers


def test_unprepared_file_is_refused_with_the_prepare_command():
    with pytest.raises(JobNotPrepared, match=r"no layerwatch snapshot trigger.*`layerwatch gcode prepare "
                                             r"part.gcode --profile octoprint -o part.gcode`"):
        check_prepared(PART_GCODE.read_bytes(), "octoprint", "part.gcode")
    with pytest.raises(JobNotPrepared, match="--profile klipper"):
        check_prepared(PART_GCODE.read_bytes(), "moonraker", "part.gcode")


def test_triggers_the_host_never_delivers_or_in_comments_do_not_count():
    # @layerwatch host commands stop at OctoPrint (plugins only); a comment is never sent
    host_only = b"".join(ln + b"\n" for ln in prepared("octoprint").splitlines() if not ln.startswith(b"M118"))
    with pytest.raises(JobNotPrepared, match=r"@layerwatch host commands only, which never reach layerwatch through"):
        check_prepared(host_only, "octoprint", "k.gcode")
    assert check_prepared(prepared("klipper"), "octoprint", "k.gcode") > 0  # OctoPrint in front of Klipper
    commented = b"G28\n; M118 E1 layerwatch snapshot layer=0 z=0.300\nG1 X1 Y1 E1\n"
    with pytest.raises(JobNotPrepared, match="no layerwatch snapshot trigger"):
        check_prepared(commented, "octoprint", "c.gcode")
    assert find_triggers(b"G28\nN12 M118 E1 layerwatch snapshot layer=3 z=1.2\n") == [(2, 3, b"M118")]


def test_park_spots_come_from_the_prepared_gcode():
    tp = read_toolpath(PART_GCODE)
    spots = park_spots(prepared("klipper"))
    assert sorted(spots) == list(range(tp.n_layers))
    for layer, (x, y, z) in spots.items():
        assert (x, y) == PARK
        assert z > tp.layers[layer].z  # lifted above the layer
    zs = [spots[k][2] for k in sorted(spots)]
    assert np.all(np.diff(zs) > 0)  # a different park height per layer: stale triggers are told apart
    assert park_spots(PART_GCODE.read_bytes()) == {}


class _Cam:
    def __init__(self):
        self.layer = None

    def set_layer(self, layer):
        self.layer = layer

    def grab(self):
        return np.zeros((20, 20, 3), np.uint8)


def test_frames_off_the_park_spot_are_rejected_with_the_reason():
    check = ParkCheck({0: (200.0, 200.0, 5.3), 1: (200.0, 200.0, 5.6)}, tolerance_mm=1.0)
    where = [(200.2, 199.9, 5.3)]
    cam = ParkedCamera(_Cam(), check, lambda: where[0])
    cam.set_layer(0)
    assert cam.grab().shape == (20, 20, 3) and cam.verdicts[0] == "parked" and cam.camera.layer == 0
    where[0] = (110.0, 100.0, 0.6)  # back on the part
    cam.set_layer(1)
    with pytest.raises(FrameNotParked, match=r"head was at X110.00 Y100.00 Z0.60, not at layer 1's park spot "
                                             r"X200.00 Y200.00 Z5.60"):
        cam.grab()
    where[0] = (200.0, 200.0, 5.3)  # parked, but for layer 0: a stale trigger of layer 1 is not taken
    with pytest.raises(FrameNotParked, match="0.30 mm in Z"):
        cam.grab()
    unknown = ParkedCamera(_Cam(), check, lambda: None)  # a host that cannot tell (OctoPrint)
    unknown.set_layer(1)
    unknown.grab()
    assert unknown.verdicts[1] == "unknown"
    with pytest.raises(ConfigError, match="--park-tolerance"):
        ParkCheck({}, tolerance_mm=float("nan"))


def _host(cls, handler):
    return cls(httpx.Client(base_url="http://printer.invalid", transport=httpx.MockTransport(handler)))


def test_replies_are_validated():
    def html(request):
        return httpx.Response(200, text="<html>login</html>", headers={"content-type": "text/html"})

    with pytest.raises(PrinterError, match="not JSON"):
        _host(OctoPrintJobs, html).current()
    with pytest.raises(PrinterError, match="sent text/html, not G-code"):
        _host(OctoPrintJobs, html).download(PrintJob("octoprint", "a.gcode"))

    def wrong_types(request):
        return httpx.Response(200, json={"state": "Printing", "job": {"file": {"path": 5}}})

    with pytest.raises(PrinterError, match="field 'path' is int"):
        _host(OctoPrintJobs, wrong_types).current()

    def big(request):
        return httpx.Response(200, content=b"G1 X1\n" * 100, headers={"content-type": "text/plain"})

    with pytest.raises(PrinterError, match="over the 100 byte limit"):
        _host(OctoPrintJobs, big).download(PrintJob("octoprint", "a.gcode"), max_bytes=100)

    def moon(request):
        if request.url.path.startswith("/server/files/gcodes/"):
            assert request.url.raw_path == b"/server/files/gcodes/sub%20dir/a%23b.gcode"
            return httpx.Response(200, content=b"G28\n", headers={"content-type": "application/octet-stream"})
        return httpx.Response(200, json={"result": {"status": {"print_stats": {"state": "printing",
                                                                               "filename": "sub dir/a#b.gcode"}}}})

    host = _host(MoonrakerJobs, moon)
    state, job = host.current()
    assert state == "printing" and job == PrintJob("moonraker", "sub dir/a#b.gcode", "gcodes")
    assert host.download(job) == b"G28\n"

    def sd(request):
        return httpx.Response(200, json={"state": "Printing", "job": {"file": {"path": "x.gco", "origin": "sdcard"}}})

    with pytest.raises(PrinterError, match="SD card"):
        _host(OctoPrintJobs, sd).download_path(_host(OctoPrintJobs, sd).current()[1])


def test_watcher_rejects_an_unprepared_job_once_and_waits_for_the_next():
    states = iter([("printing", "plain.gcode")] * 3 + [("idle", None)] + [("printing", "plain.gcode")] * 2)

    def handler(request):
        if request.url.path.startswith("/downloads/"):
            return httpx.Response(200, content=PART_GCODE.read_bytes(), headers={"content-type": "text/plain"})
        state, path = next(states)
        return httpx.Response(200, json={"state": state.title(), "job": {"file": {"path": path, "origin": "local"}}})

    rejected = []
    w = JobWatcher(_host(OctoPrintJobs, handler), start=lambda job, data: pytest.fail("must not be analysed"),
                   reject=lambda job, msg: rejected.append((job.path, msg)), poll_s=0.01, max_jobs=2)
    handled = w.run()
    # the same job is rejected once while it prints; after it ended, printing it again is a new job
    assert [o for _, o in handled] == ["not prepared", "not prepared"] and len(rejected) == 2
    assert "layerwatch gcode prepare plain.gcode --profile octoprint" in rejected[0][1]


def _fill(store, job_id, kb):
    d = store.root / store.rel(job_id) / "tops"
    d.mkdir(parents=True, exist_ok=True)
    (d / "layer_0000.png").write_bytes(b"x" * kb * 1000)


def test_retention_prunes_the_oldest_jobs_first(tmp_path):
    store = ArtifactStore(tmp_path, max_jobs=2)
    for jid, kb in ((1, 10), (2, 10), (3, 10)):
        _fill(store, jid, kb)
    assert store.prune() == [1]
    assert [j for j, _ in store.job_folders()] == [2, 3]
    by_size = ArtifactStore(tmp_path, max_mb=0.025)  # 25 kB: job 2 (10 kB) and job 3 (10 kB) fit, 4 does not
    _fill(by_size, 4, 10)
    assert by_size.prune(keep=4) == [2]
    assert [j for j, _ in by_size.job_folders()] == [3, 4]
    big = ArtifactStore(tmp_path, max_mb=0.001)
    assert big.prune(keep=4) == [3] and [j for j, _ in big.job_folders()] == [4]  # the running job stays
    with pytest.raises(ConfigError, match="--keep-jobs"):
        ArtifactStore(tmp_path, max_jobs=0)
    with pytest.raises(ConfigError, match="--keep-mb"):
        ArtifactStore(tmp_path, max_mb=float("inf"))


def test_stored_layers_reference_their_images_relative_to_the_image_folder(tmp_path):
    from layerwatch.monitor.artifacts import StoringPipeline
    from layerwatch.monitor.follow import CameraSpec, job_camera
    from layerwatch.pipeline.config import recommended_config
    from layerwatch.pipeline.step import LayerPipeline

    cfg = recommended_config(PART_CONFIG)
    tp = read_toolpath(PART_GCODE)
    cam, model = job_camera(CameraSpec(image_size=(640, 360)), tp, cfg)
    store = ArtifactStore(tmp_path)
    pipe = StoringPipeline(LayerPipeline(tp, model, cfg), store, job_id=7)
    cam.set_layer(3)
    res = pipe.process(cam.grab(), 3)
    assert isinstance(res, LayerResult) and res.status == "ok"
    assert res.images == {"top": "jobs/000007/tops/layer_0003.png", "reference": "jobs/000007/refs/layer_0003.png",
                          "overlay": "jobs/000007/overlays/layer_0003.png", "footprint": "jobs/000007/masks/layer_0003.png"}
    assert all((tmp_path / p).stat().st_size > 100 for p in res.images.values())
    assert pipe.topview is pipe.pipeline.topview  # everything else is the wrapped pipeline's
    # an alert attaches the stored overlay: its path resolves from any working directory
    from layerwatch.monitor.service import Monitor

    attached = Monitor(None, None, pipe)._overlay(res, None)
    assert attached == str(tmp_path / res.images["overlay"])
    assert Monitor(None, None, pipe.pipeline)._overlay(LayerResult(0, 0.3, images={"overlay": "o.png"}), None) == "o.png"


def test_a_job_without_a_configured_top_view_is_observed_where_its_part_is():
    from layerwatch.monitor.follow import fit_topview
    from layerwatch.pipeline.config import JobConfig

    tp = read_toolpath(PART_GCODE)
    x0, y0, x1, y1 = tp.bounds
    tv = fit_topview(JobConfig(), tp).topview
    assert tv.center_mm == ((x0 + x1) / 2, (y0 + y1) / 2)
    assert tv.width_mm == tv.height_mm >= max(x1 - x0, y1 - y0) + 30 and tv.width_mm >= 90
    # a followed job gets it when the settings leave the top view at the built-in default
    from layerwatch.monitor.follow import CameraSpec, JobService

    svc = JobService(object(), _host(MoonrakerJobs, lambda r: httpx.Response(404)), JobConfig(),
                     CameraSpec(image_size=(640, 360)), park_tolerance_mm=None)
    mon = svc.start(PrintJob("moonraker", "p.gcode", "gcodes"), prepared("klipper"))
    try:
        assert mon.pipeline.topview.center_mm == tv.center_mm
    finally:
        mon.close()


def test_m114_position_reads_only_the_reply_that_follows_its_own_request():
    """OctoPrint's log push can carry an older position line (its own M114 on a cancel, an earlier job's)
    before ours went out: that line rejected a parked frame (test_jobs_real's park-spot test, now and then)."""
    import threading

    from layerwatch.monitor.parked import M114Position

    class _Octo:
        def __init__(self):
            self.listeners, self.sent = [], []

        def send_gcode(self, line):
            self.sent.append(line)
            push = lambda logs: [f({"current": {"logs": logs}}) for f in self.listeners]  # noqa: E731
            threading.Timer(0.05, push, [["Recv: X:111.20 Y:108.71 Z:0.30 E:0.00 Count X:1 Y:1 Z:1"]]).start()
            threading.Timer(0.10, push, [["Send: M114"]]).start()
            threading.Timer(0.15, push, [["Recv: X:200.00 Y:200.00 Z:5.90 E:0.00 Count X:1 Y:1 Z:1"]]).start()

    octo = _Octo()
    position = M114Position(octo, timeout_s=2.0)
    assert position() == (200.0, 200.0, 5.9) and octo.sent == ["M114"]
