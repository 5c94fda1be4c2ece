"""History store speed: SQLite :class:`History` vs a naive JSON-file-per-layer store.

Run: ``python benchmarks/bench_history.py`` or ``pytest benchmarks/bench_history.py -s``.
Writes 1,000 layer results (two regions, images, timings each) for one job,
then times what the dashboard does on every live update: the a% curve rows
(``layer_summary`` / ``GET /api/jobs/{id}/layers``) and the full results
(``layers``). Baseline in the same run: one ``layer_XXXX.json`` file per layer
(written with ``Path.write_text``; read back by listing the folder and parsing
every file). Neither side fsyncs per layer (History runs WAL +
``synchronous=NORMAL``), so the comparison is like for like.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
import warnings
from pathlib import Path

from layerwatch.analysis.result import LayerResult, Region
from layerwatch.storage.history import History

N_LAYERS = 1000
REPEATS = 5


def _result(i: int) -> LayerResult:
    regions = [
        Region(area_mm2=3.0 + k, bbox_mm=(10.0 + k, 20.0, 14.0 + k, 25.0), centroid_mm=(12.0 + k, 22.5),
               n_blocks=4 + k, mean_similarity=0.3, min_similarity=0.1, outside_fraction=0.2)
        for k in range(2)
    ]
    return LayerResult(
        layer=i, z=0.2 * (i + 1), metric="pearson", threshold=0.45, anomaly_ratio=(i % 97) / 1000.0,
        printed_area_mm2=400.0, anomalous_area_mm2=4.0, n_blocks=900, n_anomalous=9, regions=regions,
        timings_ms={"warp": 3.1, "render": 2.2, "hog": 4.0, "metric": 0.5},
        images={k: f"layer_{i:04d}_{k}.png" for k in ("photo", "top", "reference", "overlay")},
    )


class JsonFileStore:
    """The naive baseline: one JSON file per layer in a folder per job."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def add_layer(self, job: int, result: LayerResult) -> None:
        d = self.root / f"job_{job}"
        d.mkdir(parents=True, exist_ok=True)
        (d / f"layer_{result.layer:04d}.json").write_text(result.to_json())

    def layers(self, job: int) -> list[LayerResult]:
        return [LayerResult.from_json(p.read_text()) for p in sorted((self.root / f"job_{job}").glob("layer_*.json"))]

    def layer_summary(self, job: int) -> list[dict]:
        keys = ("layer", "z", "anomaly_ratio", "status", "metric", "threshold")
        out = []
        for p in sorted((self.root / f"job_{job}").glob("layer_*.json")):
            d = json.loads(p.read_text())
            out.append({k: d[k] for k in keys})
        return out


def _best(fn, repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def run(n_layers: int = N_LAYERS) -> dict[str, float]:
    results = [_result(i) for i in range(n_layers)]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        hist = History(tmp / "history.db")
        job = hist.start_job("bench", part="bench")
        naive = JsonFileStore(tmp / "json")

        per_h, per_n = [], []
        for r in results:
            t0 = time.perf_counter()
            hist.add_layer(job, r)
            t1 = time.perf_counter()
            naive.add_layer(job, r)
            per_n.append(time.perf_counter() - t1)
            per_h.append(t1 - t0)

        assert hist.layer_summary(job) == naive.layer_summary(job)
        assert [x.to_dict() for x in hist.layers(job)] == [x.to_dict() for x in naive.layers(job)]

        out = {
            "write_ms_history": 1e3 * statistics.median(per_h),
            "write_ms_json": 1e3 * statistics.median(per_n),
            "summary_ms_history": 1e3 * _best(lambda: hist.layer_summary(job)),
            "summary_ms_json": 1e3 * _best(lambda: naive.layer_summary(job)),
            "full_ms_history": 1e3 * _best(lambda: hist.layers(job)),
            "full_ms_json": 1e3 * _best(lambda: naive.layers(job)),
        }
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                from fastapi.testclient import TestClient

                from layerwatch.web.app import create_app

            with TestClient(create_app(hist), base_url="http://127.0.0.1") as client:  # a loopback Host
                out["api_layers_ms_history"] = 1e3 * _best(lambda: client.get(f"/api/jobs/{job}/layers").raise_for_status())
        except ImportError:
            pass
        hist.close()
    return out


def report(out: dict[str, float]) -> None:
    print(f"\n{N_LAYERS} layers, one job (medians for writes, best of {REPEATS} for reads)")
    for what, key in (("per-layer write", "write_ms"), ("a% curve rows (dashboard)", "summary_ms"),
                      ("all LayerResults", "full_ms")):
        h, n = out[f"{key}_history"], out[f"{key}_json"]
        print(f"  {what:28s} History {h:8.3f} ms   JSON files {n:8.3f} ms   ratio JSON/History {n / h:6.2f}x")
    if "api_layers_ms_history" in out:
        print(f"  GET /api/jobs/{{id}}/layers through FastAPI: {out['api_layers_ms_history']:.2f} ms")


def test_bench_history():
    out = run()
    report(out)
    assert all(v > 0 for v in out.values())


if __name__ == "__main__":
    report(run())
