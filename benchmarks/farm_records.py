"""The farm path's records, for comparing two versions of the code (a speed-up must not change a verdict).

Run: ``python benchmarks/farm_records.py OUT.json [--printers 3] [--jobs 1]`` in each checkout (``PYTHONPATH`` at its
``src``), then ``python benchmarks/farm_records.py --compare A.json B.json`` (exit 1 when they differ).

Each printer of :mod:`farm_capacity` (its own shifted, gained JPEG photos of the example part) prints every
layer through a :class:`~layerwatch.farm.monitor.FarmMonitor` as the capacity benchmark runs it (camera-fault
gate, per-layer task, lag check, policy); the pool's work runs in the calling thread. Written per layer: the
record without timings (``timings_ms``, the scene channel's ``ms``, ``photo_ms``, ``trigger_to_pause_ms``) and
the SHA-1 of the overlay thumbnail. ``--same-file``: the printers share their references (the second and
third read the first one's): the file must equal the one written without it. ``--jobs J``: each printer prints
the part ``J`` times, a new job (monitor and pipeline) each time as the capacity benchmark's printers do (what a
printer keeps between its jobs, :mod:`layerwatch.pipeline.job_geometry`, must not change a record); the records
then carry their ``job``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def records(printers: int, same_file: bool = False, jobs: int = 1) -> list:
    import farm_capacity as fc  # noqa: PLC0415 - sets the thread limits before NumPy/OpenCV load

    scene = fc.Scene(layers=33)
    out = []
    for k in range(printers):
        runner, p, pool = fc.inline_printer(scene, k, same_file)
        for job in range(jobs):
            for i in range(scene.toolpath.n_layers):
                runner.frame(p, i, scene.jpeg(k, i))  # layer 0 after the first job: a new job
                assert p.mon is not None
                rec = fc._record(p.mon.report.results[-1])
                for key in ("photo_ms", "trigger_to_pause_ms"):
                    rec.pop(key, None)
                thumb = p.mon.pipeline.last_thumb
                thumb = thumb.png() if thumb is not None else None  # drawn here, as the dashboard draws it when asked
                out.append({"printer": k, "layer": i, "record": rec,
                            "thumb_sha1": hashlib.sha1(thumb).hexdigest() if thumb else None}
                           | ({"job": job} if jobs > 1 else {}))
        runner.close([p])
        pool.close()
    return out


def differences(a, b, path: str = "") -> list[str]:
    """Where two JSON values differ (NaN equals NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in ([f"{path}.{k}: only in one"] if (k in a) != (k in b) else differences(a[k], b[k], f"{path}.{k}"))]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        return [d for i, (u, v) in enumerate(zip(a, b, strict=True)) for d in differences(u, v, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", nargs="?", help="JSON file to write")
    ap.add_argument("--printers", type=int, default=3)
    ap.add_argument("--same-file", action="store_true",
                    help="the printers share their references (one file, one camera model): the records must not change")
    ap.add_argument("--jobs", type=int, default=1, help="jobs each printer prints, one after the other (default 1)")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two files written before")
    a = ap.parse_args(argv)
    if a.compare:
        x, y = (json.loads(Path(f).read_text()) for f in a.compare)
        diff = differences(x, y)
        print(f"{len(x)} vs {len(y)} layers; {len(diff)} differences", *diff[:40], sep="\n")
        return 1 if diff else 0
    if not a.out or a.printers < 1 or a.jobs < 1:
        ap.error("give OUT.json (and --printers >= 1, --jobs >= 1), or --compare A B")
    recs = records(a.printers, a.same_file, a.jobs)
    Path(a.out).write_text(json.dumps(recs, allow_nan=True))
    print(f"{len(recs)} layers written to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
