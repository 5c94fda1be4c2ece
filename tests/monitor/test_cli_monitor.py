import pytest
from typer.testing import CliRunner

from layerwatch.cli import app
from layerwatch.errors import ConfigError, PrinterError
from layerwatch.monitor.printers.octoprint import OctoPrintPrinter


@pytest.mark.slow
def test_cli_virtual_sim_pauses_on_injected_failure(tmp_path):
    r = CliRunner().invoke(app, ["monitor", "--printer", "virtual", "--camera", "sim", "--failure", "spaghetti",
                                 "--onset", "15", "--history", str(tmp_path / "h.db")])
    assert r.exit_code == 0, r.output
    assert "1 pause(s)" in r.output and "PAUSE layer 1" in r.output


def test_cli_bad_specs():
    from layerwatch.cli.monitor import open_printer

    with pytest.raises(ConfigError, match="unknown --printer"):
        open_printer("telnet://x")
    with pytest.raises(PrinterError, match="API key"):
        open_printer("octoprint://127.0.0.1:9")


def test_unreachable_octoprint_is_a_clear_error():
    with OctoPrintPrinter("octoprint://127.0.0.1:9?key=K", push=False, timeout_s=1) as p, pytest.raises(PrinterError, match="unreachable"):
        p.status()
