"""A TestClient as the dashboard page is (imported by the tests in this folder)."""

from __future__ import annotations

import warnings

import pytest

BASE = "http://127.0.0.1"  # a loopback Host: the dashboard refuses other names without a token


def dashboard_client(app, token: str | None = None, csrf: bool = True):
    """A TestClient as the dashboard page is: loopback Host, logged in (with ``token``), CSRF header set."""
    pytest.importorskip("fastapi")
    with warnings.catch_warnings():  # starlette asks for httpx2, which is not installed here
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient

    c = TestClient(app, base_url=BASE)
    if token is not None:
        assert c.get("/login", params={"token": token}, follow_redirects=False).status_code == 303
    if csrf:
        c.headers["X-CSRF-Token"] = c.get("/api/session").json()["csrf"]
    return c
