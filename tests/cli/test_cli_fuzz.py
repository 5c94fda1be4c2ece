"""Hundreds of generated bad command lines over every verb: never exit 70, never a traceback.

Two generators: a deterministic one with one known mistake per line (all must be refused, exit 2),
and hypothesis drawing random mixes of a verb's options, junk values and files (any exit but 70).

The lines come from :mod:`cli_badlines` (deterministic, read from the app's own command tree);
each is run in-process through :func:`layerwatch.cli.main` with stderr captured.
``python tests/cli/cli_badlines.py`` prints the same histogram and every finding.
"""

from __future__ import annotations

import os
import re
from collections import Counter

import pytest
from cli_badlines import bad_lines, leaf_commands, make_fixtures, run_all, run_line
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

# a logging record (the monitor logs where its settings come from before it reads its inputs)
_LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ [A-Z]+ ")


def test_bad_command_lines_are_refused_in_one_line(tmp_path):
    lines = bad_lines(tmp_path)
    results, hist = run_all(lines, tmp_path)
    print(f"{len(lines)} bad command lines: exit codes {dict(sorted(hist.items()))}")

    assert len(lines) >= 300
    groups = {p[0] for p in leaf_commands() if len(p) > 1}  # verbs with sub-verbs: gcode, config
    verbs = Counter(" ".join(r.argv[:2]) if r.argv[0] in groups else r.argv[0] for r in results)
    assert all(verbs[" ".join(p)] >= 5 for p in leaf_commands()), verbs  # every verb is fuzzed
    crashed = [r for r in results if r.code == 70 or r.traceback or not isinstance(r.code, int)]
    assert not crashed, "\n".join(f"{r.code}: {' '.join(r.argv)} -> {r.stderr[:300]}" for r in crashed)
    assert not list(tmp_path.glob("layerwatch-crash-*"))
    accepted = [r for r in results if r.code in (0, "work")]
    assert not accepted, [" ".join(r.argv) for r in accepted]  # every line holds a mistake
    for r in results:
        errors = [ln for ln in r.stderr_lines if not _LOG_LINE.match(ln)]
        assert len(errors) == 1 and errors[0].startswith("error: "), (r.argv, r.stderr)
    assert set(hist) <= {"1", "2"}


# --- random command lines (hypothesis): any mix of a verb's options, junk values and fixture files ---

_JUNK = ("nan", "-inf", "1e999", "-1", "0", "1", "7", "0.5", "1e9", "abc", "", "[markers]", "-", "--",
         "1,2", "spaghetti@3", "/dev/null", "/proc/layerwatch-missing/x", "\udcff", "é", "-h")


@pytest.fixture(scope="module")
def fuzz_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("hyp")
    return root, make_fixtures(root / "fixtures")


@st.composite
def _command_lines(draw, fx):
    leaves = leaf_commands()
    path = draw(st.sampled_from(sorted(leaves)))
    cmd = leaves[path]
    opts = [o for p in cmd.params if p.param_type_name == "option" for o in p.opts if o not in ("-h", "--help")]
    files = [str(v) for k, v in sorted(fx.items()) if k != "out"]
    token = st.one_of(st.sampled_from(opts or ["--bogus"]), st.sampled_from(_JUNK), st.sampled_from(files),
                      st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=6))
    return [*path, *draw(st.lists(token, max_size=6))]


@pytest.mark.slow
def test_random_command_lines_never_crash(fuzz_root):
    root, fx = fuzz_root
    seen: Counter = Counter()

    @settings(max_examples=int(os.environ.get("LAYERWATCH_CLI_FUZZ_EXAMPLES", 150)), deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
    @given(_command_lines(fx))
    def check(argv):
        r = run_line(argv, cwd=root)
        seen[str(r.code)] += 1
        assert r.code in (0, 1, 2, "work") and not r.traceback, (r.code, argv, r.stderr[:300])
        if r.code == 2:
            errors = [ln for ln in r.stderr_lines if not _LOG_LINE.match(ln)]
            assert len(errors) == 1 and errors[0].startswith("error: "), (argv, r.stderr)

    check()
    print(f"random command lines: {dict(sorted(seen.items()))}")
    assert not list(root.glob("layerwatch-crash-*"))
