"""Markers of the monitor tests (registered here; --strict-markers is on)."""


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "moonraker: needs a real Moonraker + Klippy (installed by .ci/install-moonraker)")
