"""Structure figures of issue 17: long functions and modules, function-local imports, package cycles.

Usage: ``python tools/structure_figures.py [src/layerwatch]``. Prints the functions over 80 lines, the
modules over 600 lines, every import statement inside a function (file:line) and the pairs of packages
that import each other.
"""

from __future__ import annotations

import ast
import collections
import pathlib
import sys


def main(root: pathlib.Path) -> None:
    long_funcs, long_mods, local_imports = [], [], set()
    deps: dict[str, set[str]] = collections.defaultdict(set)
    for path in sorted(root.rglob("*.py")):
        src = path.read_text()
        if src.count("\n") > 600:
            long_mods.append(f"{path} ({src.count(chr(10))} lines)")
        tree = ast.parse(src)
        package = path.relative_to(root).parts[0].removesuffix(".py")
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if node.end_lineno - node.lineno + 1 > 80:
                    long_funcs.append(f"{path}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)")
                local_imports |= {f"{path}:{sub.lineno}" for sub in ast.walk(node)
                                  if isinstance(sub, (ast.Import, ast.ImportFrom))}
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith(f"{root.name}."):
                target = node.module.split(".")[1]
                if target != package:
                    deps[package].add(target)
    cycles = sorted({tuple(sorted((a, b))) for a in deps for b in deps[a] if a in deps.get(b, ())})
    print(f"functions over 80 lines: {len(long_funcs)}", *long_funcs, sep="\n  ")
    print(f"modules over 600 lines: {len(long_mods)}", *long_mods, sep="\n  ")
    print(f"function-local imports: {len(local_imports)}", *sorted(local_imports), sep="\n  ")
    print(f"packages importing each other: {len(cycles)}", *cycles, sep="\n  ")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "src/layerwatch"))
