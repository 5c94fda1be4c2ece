"""Schemathesis against the dashboard's OpenAPI schema (in-process ASGI), with a fixed budget.

Two properties over every route and generated input: no 5xx answer, and no
state-changing request that comes cross-site (foreign ``Origin``, no CSRF
token) gets through.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, settings  # noqa: E402
from seed_history import seed_job  # noqa: E402

from layerwatch.storage.history import History  # noqa: E402
from layerwatch.web.app import create_app  # noqa: E402
from layerwatch.web.virtual import virtual_printer  # noqa: E402

pytestmark = [
    pytest.mark.filterwarnings("ignore::DeprecationWarning"),
    pytest.mark.filterwarnings("ignore::PendingDeprecationWarning"),
    pytest.mark.filterwarnings("ignore:.*httpx2.*"),
]
BUDGET = settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck))
UNSAFE = {"POST", "PUT", "PATCH", "DELETE"}

_ROOT = Path(tempfile.mkdtemp(prefix="lw-fuzz-"))
_HIST = History(_ROOT / "history.db")
seed_job(_HIST, _ROOT, n_layers=8, fail_at=4, images=True)
# schemathesis' ASGI client sends Host: testserver; the test admits that name besides loopback
APP = create_app(_HIST, printers={"virtual": virtual_printer()}, image_root=_ROOT, allowed_hosts=["testserver"])
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

    _PAGE = TestClient(APP)
    _CSRF = _PAGE.get("/api/session").json()["csrf"]
    _COOKIES = dict(_PAGE.cookies)
    schema = schemathesis.openapi.from_asgi("/openapi.json", APP).exclude(path="/api/stream")


def _call(case, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return case.call(**kw)


@schema.parametrize()
@BUDGET
def test_no_server_errors(case):
    response = _call(case, headers={"X-CSRF-Token": _CSRF}, cookies=_COOKIES)
    assert response.status_code < 500, (case.method, case.formatted_path, response.text[:200])


@schema.parametrize()
@BUDGET
def test_cross_site_requests_change_nothing(case):
    if case.method.upper() not in UNSAFE:
        return
    before = (_HIST.revision(), _HIST.audit(limit=1), _HIST.setting("job_config"))
    response = _call(case, headers={"Origin": "https://evil.example", "Sec-Fetch-Site": "cross-site"}, cookies=_COOKIES)
    assert response.status_code == 403, (case.method, case.formatted_path, response.status_code)
    assert (_HIST.revision(), _HIST.audit(limit=1), _HIST.setting("job_config")) == before
