"""Dashboard page render: page load to "curve drawn" in headless Debian chromium.

Run: ``python benchmarks/bench_dashboard.py`` or ``pytest benchmarks/bench_dashboard.py -s``
(``make bench``). Target (issue 10): dashboard pages render in < 300 ms from
the local server with 1,000 layers of history.

A history is seeded with :func:`seed_history.seed_job` (``tests/web/seed_history.py``) (a live job of
300 and one of 1,000 layers, images every 10th layer and for the failing
ones, plus two finished jobs), ``layerwatch serve --virtual`` serves it on
127.0.0.1 in its own process, and chromium (``/usr/bin/chromium`` through Playwright, headless,
a fresh browser context per load: nothing cached) opens ``/``. The page's own
clock gives the figure (the page opens the job from its ``/#job=ID`` link): ``performance.now()`` (0 = navigation start) in the
first animation frame after the a% polyline holds every layer of the job.
So it covers the HTML, CSS and JS requests, the API calls
(settings, metrics, jobs, layers, latest, events, printers) and the drawing.

Baselines, measured in the same process on the same data, loads interleaved:

* ``json-files``: the same app and page (uvicorn, its own process) over a JSON-file-per-layer store
  (one ``layer_XXXX.json`` per layer, a ``job.json`` with running totals and
  an ``events.json`` per job; the naive store of ``bench_history.py``);
* ``full-api``: the same SQLite history, but the page asks for the unpaginated
  full history (``/api/jobs/{id}/layers?full=true``: whole LayerResults) instead
  of the light curve rows (request rewritten by Playwright); its ratio is taken
  against ``lw-routed``, the page's own request passed through the same
  Playwright interception unchanged, so the interception cost cancels.

Printed: median and p90 per variant, the in-page duration of the layers
request (Resource Timing), the ratio baseline / layerwatch of the medians and
the load average (the figures swing with other work on the machine). No
timing is asserted.
"""

from __future__ import annotations

import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any

from layerwatch.analysis.result import LayerResult
from layerwatch.storage.history import History

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "web"))  # test-only history seeder
from seed_history import seed_job  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--no-first-run", "--disable-sync"]
SIZES = (300, 1000)
REPEATS = int(os.environ.get("LAYERWATCH_BENCH_REPEATS", "20"))
WARMUP = 2
TARGET_MS = 300.0

# Recorded in the page: when the polyline has all points, and the next animation frame (drawn).
PROBE = """
window.__lw = {};
new MutationObserver(() => {
  if (window.__lw.dom) { return; }
  const p = document.querySelector('#curve polyline');
  if (!p) { return; }
  const n = p.getAttribute('points').trim().split(/\\s+/).length;
  if (n >= %d) {
    window.__lw.dom = performance.now();
    requestAnimationFrame(() => { window.__lw.drawn = performance.now(); });
  }
}).observe(document, {subtree: true, childList: true});
"""


class JsonFileHistory:
    """The naive baseline store: the :class:`History` methods the app and the seeder use, over JSON files.

    ``root/job_N/job.json`` (job row with running ``n_layers``/``max_anomaly_ratio``),
    ``root/job_N/layer_XXXX.json`` (one LayerResult each), ``root/job_N/events.json``.
    """

    _KEYS = ("layer", "z", "anomaly_ratio", "status", "metric", "threshold")

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._settings = self.root / "settings.json"

    # -- writing (seed_job) --------------------------------------------------------
    def _dir(self, job: int) -> Path:
        return self.root / f"job_{int(job)}"

    def _read(self, path: Path, default: Any = None) -> Any:
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return default

    def start_job(self, printer: str, gcode_path=None, gcode_hash=None, part=None, config=None) -> int:
        with self._lock:
            job = 1 + max((int(p.name[4:]) for p in self.root.glob("job_*")), default=0)
            d = self._dir(job)
            d.mkdir()
            cfg = config.model_dump(mode="json") if hasattr(config, "model_dump") else config
            row = {"id": job, "printer": printer, "gcode_path": None if gcode_path is None else str(gcode_path),
                   "gcode_hash": gcode_hash, "part": part, "config": cfg, "started": time.time(), "ended": None,
                   "outcome": None, "n_layers": 0, "max_anomaly_ratio": None}
            (d / "job.json").write_text(json.dumps(row))
            (d / "events.json").write_text("[]")
            return job

    def add_layer(self, job: int, result: LayerResult) -> None:
        with self._lock:
            d = self._dir(job)
            (d / f"layer_{result.layer:04d}.json").write_text(result.to_json())
            row = self._read(d / "job.json")
            row["n_layers"] += 1
            a = result.anomaly_ratio
            row["max_anomaly_ratio"] = a if row["max_anomaly_ratio"] is None else max(a, row["max_anomaly_ratio"])
            (d / "job.json").write_text(json.dumps(row))

    def add_event(self, job: int, kind: str, message: str, data: Any = None) -> int:
        with self._lock:
            path = self._dir(job) / "events.json"
            events = self._read(path, [])
            eid = 1 + max((e["id"] for j in self.root.glob("job_*") for e in self._read(j / "events.json", [])),
                          default=0)
            events.append({"id": eid, "time": time.time(), "kind": kind, "message": message, "data": data})
            path.write_text(json.dumps(events))
            return eid

    def end_job(self, job: int, outcome: str) -> None:
        with self._lock:
            path = self._dir(job) / "job.json"
            row = self._read(path)
            row["ended"], row["outcome"] = time.time(), outcome
            path.write_text(json.dumps(row))

    def set_setting(self, name: str, value: Any) -> None:
        data = self._read(self._settings, {})
        data[name] = value.model_dump(mode="json") if hasattr(value, "model_dump") else value
        self._settings.write_text(json.dumps(data))

    # -- reading (the app) -----------------------------------------------------------
    def jobs(self) -> list[dict[str, Any]]:
        rows = [self._read(p / "job.json") for p in self.root.glob("job_*")]
        for r in rows:
            r.pop("config", None)
        return sorted(rows, key=lambda r: -r["id"])

    def last_job_id(self) -> int | None:
        return max((int(p.name[4:]) for p in self.root.glob("job_*")), default=None)

    def job(self, job_id: int) -> dict[str, Any] | None:
        row = self._read(self._dir(job_id) / "job.json")
        if row is not None:
            row.pop("n_layers"), row.pop("max_anomaly_ratio")
        return row

    def _layer_files(self, job_id: int) -> list[Path]:
        return sorted(self._dir(job_id).glob("layer_*.json"))

    def layers(self, job_id: int) -> list[LayerResult]:
        return [LayerResult.from_json(p.read_text()) for p in self._layer_files(job_id)]

    def layer_summary(self, job_id: int, after: int = -1) -> list[dict[str, Any]]:
        out = []
        for p in self._layer_files(job_id):
            d = json.loads(p.read_text())
            if d["layer"] > after:
                out.append({k: d[k] for k in self._KEYS})
        return out

    def latest_layer(self, job_id: int) -> LayerResult | None:
        files = self._layer_files(job_id)
        return LayerResult.from_json(files[-1].read_text()) if files else None

    def events(self, job_id: int, after: int = 0) -> list[dict[str, Any]]:
        return [e for e in self._read(self._dir(job_id) / "events.json", []) if e["id"] > after]

    def revision(self) -> tuple[float, ...]:
        return tuple(p.stat().st_mtime for p in sorted(self.root.glob("job_*")))

    def setting(self, name: str) -> Any | None:
        return self._read(self._settings, {}).get(name)

    path = None  # no database file (the app keeps such files from being served)

    def is_artifact(self, path: str) -> bool:
        """True when a stored layer refers to the image ``path`` (the app serves only those).

        The paths are collected once (as History keeps them in a table) so that image requests
        do not weigh on the page-load figures; the benchmark writes no layers while serving.
        """
        if getattr(self, "_artifacts", None) is None:
            self._artifacts = {v for j in self.root.glob("job_*") for p in j.glob("layer_*.json")
                               for v in json.loads(p.read_text()).get("images", {}).values()}
        return path in self._artifacts

    def audit(self, after: int = 0, limit: int = 200) -> list[dict[str, Any]]:
        return []  # the baseline records no dashboard actions (the page reads the audit log)


def seed(history: Any, root: Path) -> dict[int, int]:
    """The same jobs in any store: two finished ones, then live jobs of :data:`SIZES` layers; {layers: job id}."""
    seed_job(history, root, n_layers=120, fail_at=None, outcome="done", part="bracket", seed=11)
    seed_job(history, root, n_layers=200, fail_at=150, outcome="cancelled", part="vase", seed=12)
    return {n: seed_job(history, root, n_layers=n, fail_at=int(0.9 * n), part=f"tower {n}", seed=n) for n in SIZES}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sk:
        sk.bind(("127.0.0.1", 0))
        return sk.getsockname()[1]


class Server:
    """A dashboard server process on 127.0.0.1 (``layerwatch serve``, or the JSON-store app).

    Its own process, as users run it: it shares no interpreter lock with Playwright's client.
    """

    def __init__(self, store: str, root: Path) -> None:
        import httpx

        port = _free_port()
        self.url = f"http://127.0.0.1:{port}"
        if store == "sqlite":
            exe = Path(sys.executable).with_name("layerwatch")
            cmd = [str(exe), "serve", "--db", str(root / "history.db"), "--images", str(root), "--port", str(port),
                   "--virtual"]
        else:
            cmd = [sys.executable, __file__, "--serve-json", str(root), str(port)]
        self.log = tempfile.TemporaryFile()
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=self.log)
        for _ in range(600):
            if self.proc.poll() is not None:
                self.log.seek(0)
                raise RuntimeError(f"dashboard server exited: {self.log.read().decode()[-500:]}")
            try:
                if httpx.get(self.url + "/api/jobs", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                time.sleep(0.05)
        self.close()
        raise RuntimeError(f"dashboard did not start on {self.url}")

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


def serve_json(root: Path, port: int) -> None:
    """The baseline server: the same app over :class:`JsonFileHistory` (like ``layerwatch serve``)."""
    import uvicorn

    from layerwatch.web.app import create_app
    from layerwatch.web.virtual import virtual_printer

    app = create_app(JsonFileHistory(root), printers={"virtual": virtual_printer()}, image_root=root)
    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


def _load(browser, url: str, job: int, n_layers: int, layers_route: str | None) -> dict[str, float]:
    """One cold page load of job ``job``; ``performance.now()`` values in ms plus the wall time seen from Python.

    ``layers_route``: ``None`` (no interception), ``"pass"`` (requests for the layers go through
    Playwright unchanged) or ``"full"`` (rewritten to ``?full=true``).
    """
    ctx = browser.new_context(viewport={"width": 1280, "height": 1100})
    try:
        ctx.add_init_script(PROBE % n_layers)
        if layers_route == "full":
            ctx.route("**/api/jobs/*/layers", lambda route: route.continue_(url=route.request.url + "?full=true"))
        elif layers_route == "pass":
            ctx.route("**/api/jobs/*/layers", lambda route: route.continue_())
        page = ctx.new_page()
        t0 = time.perf_counter()
        page.goto(f"{url}/#job={job}")
        page.wait_for_function("() => window.__lw && window.__lw.drawn", polling="raf", timeout=60_000)  # a function: the CSP forbids eval
        wall = 1e3 * (time.perf_counter() - t0)
        got = page.evaluate("window.__lw")
        api = page.evaluate("performance.getEntriesByType('resource').filter(e => /\\/layers/.test(e.name))"
                            ".map(e => e.responseEnd - e.startTime)[0]")
        shown = page.evaluate("document.querySelector('#curve polyline').getAttribute('points').trim().split(/\\s+/).length")
        assert shown == n_layers, (shown, n_layers)
        return {"drawn": got["drawn"], "dom": got["dom"], "wall": wall, "layers_api": api}
    finally:
        ctx.close()


def _stats(xs: list[float]) -> tuple[float, float]:
    xs = sorted(xs)
    return statistics.median(xs), xs[min(len(xs) - 1, round(0.9 * (len(xs) - 1)))]


def run(repeats: int = REPEATS) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    out: dict[str, Any] = {"loadavg_before": os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix="lw-bench-dash-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        hist = History(tmp / "sqlite" / "history.db")
        ids_sql = seed(hist, tmp / "sqlite")
        hist.close()
        t1 = time.perf_counter()
        files = JsonFileHistory(tmp / "json")
        ids_json = seed(files, tmp / "json")
        t2 = time.perf_counter()
        out["seed_s"] = {"sqlite": t1 - t0, "json-files": t2 - t1}
        servers = {"sqlite": Server("sqlite", tmp / "sqlite"), "json-files": Server("json-files", tmp / "json")}
        variants = {  # name: (server, job ids, interception of the layers request)
            "layerwatch": ("sqlite", ids_sql, None),
            "json-files": ("json-files", ids_json, None),
            "lw-routed": ("sqlite", ids_sql, "pass"),  # same interception cost as full-api
            "full-api": ("sqlite", ids_sql, "full"),
        }
        times: dict[tuple[str, int], list[dict[str, float]]] = {(v, n): [] for v in variants for n in SIZES}
        try:
            with warnings.catch_warnings(), sync_playwright() as pw:
                warnings.simplefilter("ignore")
                browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=ARGS)
                try:
                    plan = [(v, n) for n in SIZES for v in variants]
                    for k in range(WARMUP + repeats):
                        # interleaved, and the order rotates each round: load drift and order effects hit all alike
                        for v, n in plan[k % len(plan):] + plan[:k % len(plan)]:
                            srv, ids, route = variants[v]
                            t = _load(browser, servers[srv].url, ids[n], n, route)
                            if k >= WARMUP:
                                times[(v, n)].append(t)
                finally:
                    browser.close()
        finally:
            for srv in servers.values():
                srv.close()
    out["times"] = times
    out["loadavg"] = os.getloadavg()
    return out


def report(out: dict[str, Any]) -> None:
    times = out["times"]
    reps = len(next(iter(times.values())))
    print(f"\ndashboard page load to 'curve drawn', headless {CHROMIUM} ({reps} cold loads each, "
          f"interleaved; in-page performance.now(), 0 = navigation start)")
    print(f"  seeding: SQLite {out['seed_s']['sqlite']:.1f} s, JSON files {out['seed_s']['json-files']:.1f} s; "
          f"1-min load average {out['loadavg_before'][0]:.1f} before, {out['loadavg'][0]:.1f} after "
          f"(this benchmark included) on {os.cpu_count()} CPUs")
    for n in SIZES:
        med_of = {}
        for v, base in (("layerwatch", None), ("json-files", "layerwatch"), ("lw-routed", None),
                        ("full-api", "lw-routed")):
            med, p90 = _stats([t["drawn"] for t in times[(v, n)]])
            dmed, _ = _stats([t["dom"] for t in times[(v, n)]])
            wmed, _ = _stats([t["wall"] for t in times[(v, n)]])
            amed, _ = _stats([t["layers_api"] for t in times[(v, n)]])
            med_of[v] = med
            if v == "layerwatch":
                ok = ["met" if x < TARGET_MS else "NOT met" for x in (med, p90)]
                tail = f"  target < {TARGET_MS:.0f} ms: median {ok[0]}, p90 {ok[1]}"
            elif base is None:
                tail = "  (layers request routed through Playwright unchanged)"
            else:
                tail = f"  ratio {v}/{base} {med / med_of[base]:5.2f}x"
            print(f"  {n:5d} layers  {v:10s} median {med:6.1f} ms  p90 {p90:6.1f} ms  (in DOM {dmed:6.1f},"
                  f" layers request {amed:5.1f}, wall from Python {wmed:6.1f} ms){tail}")


def test_bench_dashboard():
    import pytest

    pytest.importorskip("playwright.sync_api")
    pytest.importorskip("uvicorn")
    if not CHROMIUM.exists():
        pytest.skip("Debian chromium (/usr/bin/chromium) is not installed")
    out = run()
    report(out)
    assert all(t["drawn"] > 0 for ts in out["times"].values() for t in ts)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--serve-json"]:
        serve_json(Path(sys.argv[2]), int(sys.argv[3]))
    else:
        report(run())
