"""Property-based API fuzzing from the app's own OpenAPI schema: no request may cause a 5xx."""

from __future__ import annotations

import warnings

import pytest
from hypothesis import HealthCheck, given, settings

schemathesis = pytest.importorskip("schemathesis")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import fastapi.testclient  # noqa: F401  (imported once here so its deprecation warning is not raised later)

from layerwatch.web.app import create_app  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::PendingDeprecationWarning")


def test_no_server_errors(seeded, printer):
    history, root, _ = seeded
    app = create_app(history, printers={"virtual": printer}, image_root=root, poll_s=0.0)
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    seen = []
    for result in schema.get_all_operations():
        op = result.ok()
        seen.append(f"{op.method.upper()} {op.path}")

        @given(case=op.as_strategy())
        @settings(max_examples=6, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        def check(case):
            if case.path == "/api/stream":
                case.query = {"limit": 1}
            response = case.call()
            assert response.status_code < 500, (case.method, case.path, response.status_code, response.text[:300])

        check()
    assert "PUT /api/settings" in seen and "POST /api/printers/{name}/{action}" in seen
