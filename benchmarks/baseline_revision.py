"""Load layerwatch as it was at another git revision, in this process, beside the current one.

A benchmark that claims a speed-up must time the old code in the same
process on the same inputs. :func:`load_revision` extracts ``src/layerwatch``
of ``rev`` with ``git archive`` into a temporary folder, imports the named
modules from it under their own name (``layerwatch.*``) while the current
package is set aside in ``sys.modules``, then puts the current package back.
The old modules keep their own globals (every import in the pipeline's path
is at module top), so their functions run the old code; nothing is copied
into the source tree and no source is rewritten.

Returns ``None`` when the revision cannot be extracted (no git, a shallow
clone, an unknown commit); the caller then says so and falls back to a
baseline it can build from the current package.
"""

from __future__ import annotations

import atexit
import importlib
import shutil
import subprocess
import sys
import tempfile
import types
from pathlib import Path

__all__ = ["load_revision"]

_ROOT = Path(__file__).resolve().parents[1]


def _set_aside() -> dict[str, types.ModuleType]:
    """Remove every ``layerwatch`` module from ``sys.modules`` and return them."""
    names = [n for n in sys.modules if n == "layerwatch" or n.startswith("layerwatch.")]
    return {n: sys.modules.pop(n) for n in names}


def load_revision(rev: str, modules: list[str]) -> dict[str, types.ModuleType] | None:
    """Import ``modules`` (dotted names under ``layerwatch``) as they were at git revision ``rev``.

    Parameters
    ----------
    rev : str
        Commit, tag or branch known to the repository of this checkout.
    modules : list of str
        Module names to import, e.g. ``["layerwatch.pipeline.step"]``.

    Returns
    -------
    dict of str to module, or None
        The old modules by name; ``None`` when ``rev`` cannot be extracted.
    """
    tmp = Path(tempfile.mkdtemp(prefix=f"layerwatch-{rev[:12]}-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # the old modules are used until the end
    try:
        archive = subprocess.run(["git", "-C", str(_ROOT), "archive", "--format=tar", rev, "src/layerwatch"],
                                 capture_output=True, check=False)
        if archive.returncode != 0:
            shutil.rmtree(tmp, ignore_errors=True)
            return None
        subprocess.run(["tar", "-x", "-C", str(tmp)], input=archive.stdout, check=True)
    except (OSError, subprocess.CalledProcessError):
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    current = _set_aside()
    sys.path.insert(0, str(tmp / "src"))
    try:
        old = {name: importlib.import_module(name) for name in modules}
    finally:
        sys.path.remove(str(tmp / "src"))
        _set_aside()
        sys.modules.update(current)
    return old
