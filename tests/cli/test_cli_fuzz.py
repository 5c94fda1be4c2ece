"""Hundreds of generated bad command lines over every verb: never exit 70, never a traceback.

The lines come from :mod:`cli_badlines` (deterministic, read from the app's own command tree);
each is run in-process through :func:`layerwatch.cli.main` with stderr captured.
``python tests/cli/cli_badlines.py`` prints the same histogram and every finding.
"""

from __future__ import annotations

import re
from collections import Counter

from cli_badlines import bad_lines, leaf_commands, run_all

# a logging record (the monitor logs where its settings come from before it reads its inputs)
_LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ [A-Z]+ ")


def test_bad_command_lines_are_refused_in_one_line(tmp_path):
    lines = bad_lines(tmp_path)
    results, hist = run_all(lines, tmp_path)
    print(f"{len(lines)} bad command lines: exit codes {dict(sorted(hist.items()))}")

    assert len(lines) >= 300
    verbs = Counter(" ".join(r.argv[:2]) if r.argv[0] == "gcode" else r.argv[0] for r in results)
    assert all(verbs[" ".join(p)] >= 10 for p in leaf_commands()), verbs  # every verb is fuzzed
    crashed = [r for r in results if r.code == 70 or r.traceback or not isinstance(r.code, int)]
    assert not crashed, "\n".join(f"{r.code}: {' '.join(r.argv)} -> {r.stderr[:300]}" for r in crashed)
    assert not list(tmp_path.glob("layerwatch-crash-*"))
    accepted = [r for r in results if r.code in (0, "work")]
    assert not accepted, [" ".join(r.argv) for r in accepted]  # every line holds a mistake
    for r in results:
        errors = [ln for ln in r.stderr_lines if not _LOG_LINE.match(ln)]
        assert len(errors) == 1 and errors[0].startswith("error: "), (r.argv, r.stderr)
    assert set(hist) <= {"1", "2"}
