"""HTML report and the history/report CLI verbs."""

from __future__ import annotations

import base64
import re
import stat

import numpy as np
import pytest

from layerwatch.analysis.result import LayerResult
from layerwatch.cli import main
from layerwatch.storage.history import History
from layerwatch.web.report import build_report
from layerwatch.web.token import load_or_create_token


@pytest.fixture
def image_root(tmp_path):
    import cv2

    root = tmp_path / "results"
    root.mkdir()
    rng = np.random.default_rng(0)
    for kind in ("top", "reference", "overlay"):
        cv2.imwrite(str(root / f"layer_0009_{kind}.png"), rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    return root


@pytest.fixture
def history(tmp_path):
    """Ten layers; a% passes the default 10 % pause threshold first at layer 9 (15 %)."""
    h = History(tmp_path / "history.db")
    job = h.start_job("virtual", gcode_path="part.gcode", gcode_hash="ab12", part="part")
    for i in range(10):
        ratio = 0.002 * i if i < 7 else 0.05 * (i - 6)
        h.add_layer(job, LayerResult(layer=i, z=0.3 * (i + 1), anomaly_ratio=ratio,
                                     images={k: f"layer_{i:04d}_{k}.png" for k in ("top", "reference", "overlay")}))
    h.add_event(job, "pause", "a% above 10 % at layer 9", {"layer": 9})
    yield h
    h.close()


def test_report_self_contained(history, image_root, tmp_path):
    path = build_report(history, 1, tmp_path / "out", image_root=image_root)
    text = path.read_text()
    assert "layer 9 (a% 15.0 %" in text  # default pause 10 %; layer 8 has 10 % (not above), layer 9 15 %
    imgs = re.findall(r'src="data:image/png;base64,([^"]+)"', text)
    assert len(imgs) >= 4 and all(base64.b64decode(b)[:4] == b"\x89PNG" for b in imgs)
    assert "http" not in text.replace("http-equiv", "")  # nothing fetched from elsewhere


def test_cli_history_and_report(history, image_root, tmp_path, capsys):
    db = str(history.path)
    assert main(["history", "--db", db]) == 0
    assert "virtual" in capsys.readouterr().out
    assert main(["report", "1", "--db", db, "-o", str(tmp_path / "r"), "--images", str(image_root)]) == 0
    assert (tmp_path / "r" / "report.html").is_file()
    assert main(["report", "42", "--db", db, "-o", str(tmp_path / "r")]) == 2


def test_history_and_report_leave_no_database_behind_a_mistyped_db(tmp_path, capsys, monkeypatch):
    """The read-only verbs create no database (nor its folders): a --db naming none is exit 2, no default is 0 jobs."""
    missing = tmp_path / "typo" / "histroy.db"
    assert main(["history", "--db", str(missing)]) == 2
    assert main(["report", "1", "--db", str(missing), "-o", str(tmp_path / "rep")]) == 2
    assert not (tmp_path / "typo").exists()
    monkeypatch.setenv("LAYERWATCH_DB", str(missing))  # the default database, not made yet
    capsys.readouterr()
    assert main(["history"]) == 0 and "0 job(s): no history database at" in capsys.readouterr().out
    assert main(["report", "1", "-o", str(tmp_path / "rep")]) == 2
    assert not (tmp_path / "typo").exists()


def test_token_created_0600_once(tmp_path):
    p = tmp_path / "cfg" / "token"
    tok, created = load_or_create_token(p)
    assert created and len(tok) >= 24 and stat.S_IMODE(p.stat().st_mode) == 0o600
    assert load_or_create_token(p) == (tok, False)


def test_serve_help(capsys):
    assert main(["serve", "--help"]) == 0
    assert "--host" in capsys.readouterr().out
