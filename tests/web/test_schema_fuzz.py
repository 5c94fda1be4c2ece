"""Schemathesis against the dashboard's OpenAPI schema (in-process ASGI): no 500s."""

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

_ROOT = Path(tempfile.mkdtemp(prefix="lw-fuzz-"))
_HIST = History(_ROOT / "history.db")
seed_job(_HIST, _ROOT, n_layers=8, fail_at=4, images=True)
APP = create_app(_HIST, printers={"virtual": virtual_printer()}, image_root=_ROOT)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    schema = schemathesis.openapi.from_asgi("/openapi.json", APP).exclude(path="/api/stream")


@schema.parametrize()
@settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        response = case.call()
    assert response.status_code < 500, (case.method, case.formatted_path, response.text[:200])
