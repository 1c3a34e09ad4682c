#!/usr/bin/env python3
"""Checks that every module the given Python files import can be found by this interpreter.

    python3 scripts/check-python-imports.py FILE_OR_DIR...

Every `import x` / `from x import y` in each file (at any depth: the tools import their heavy
packages inside functions) names a top-level module; the standard library's, and the files that
sit beside the importing file, in ipc/python (chunkrt's IPC mirror) or in tools/python (the
tools the test scripts of tests/python import), are local. Each other one
must be importable here (`importlib.util.find_spec`, nothing is executed). `.ci/run` runs it after
its installs with the interpreter the tests use, so a tool that imports a package no install step
provides fails here, by name, instead of deep inside a test.
Exits 1 and names file:line and module for each missing one.
"""
import ast
import importlib.util
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
LOCAL_DIRS = [ROOT / "ipc" / "python", ROOT / "tools" / "python"]


def files(args):
    for a in args:
        p = pathlib.Path(a)
        if p.is_dir():
            yield from sorted(q.resolve() for q in p.glob("*.py"))
        else:
            yield p.resolve()


def imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module.split(".")[0]


def is_local(module, path):
    return any((d / f"{module}.py").exists() or (d / module).is_dir()
               for d in [path.parent, *LOCAL_DIRS])


def main():
    if len(sys.argv) < 2:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    missing, checked = [], set()
    for path in files(sys.argv[1:]):
        for line, module in imports(path):
            if module in sys.stdlib_module_names or is_local(module, path):
                continue
            checked.add(module)
            if importlib.util.find_spec(module) is None:
                missing.append(f"{path.relative_to(ROOT)}:{line}: {module}")
    for m in missing:
        print(f"check-python-imports: not installed for {sys.executable}: {m}", file=sys.stderr)
    if missing:
        return 1
    print(f"check-python-imports: {len(checked)} packages found ({', '.join(sorted(checked))})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
