"""Write jaxlens/__init__.pyi, the stub that shows type checkers and editors the public
names `jaxlens/__init__.py` loads on first use, from that file's `_MODULES`.

usage: python tools/make_stub.py [--check]

`--check` writes nothing and exits with status 1 when the stub is not what this would
write (tests/test_stub.py runs it). A tool for the repository, not part of the package:
the wheel ships the stub, not its generator. `_MODULES` is read from the source (`ast`),
so this imports nothing of jaxlens and runs without its dependencies.
"""

import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "jaxlens"
LINE_MAX = 100  # ruff's line length (pyproject.toml)

HEADER = '''\
"""The public names of jaxlens and where each is defined, for type checkers and editors.

`jaxlens/__init__.py` loads these names on first use (`_MODULES`); this stub names them
statically. Written by tools/make_stub.py from `_MODULES`: rerun it, do not edit.
"""
'''


def modules(init: Path = PACKAGE / "__init__.py") -> dict[str, tuple[str, ...]]:
    """`_MODULES` of `init`: each private module and the public names it defines."""
    for node in ast.parse(init.read_text()).body:
        targets = [getattr(t, "id", None) for t in getattr(node, "targets", [])]
        if targets == ["_MODULES"]:
            return ast.literal_eval(node.value)
    raise SystemExit(f"{init}: no _MODULES assignment")


def _order(name: str) -> tuple:
    # ruff's import sorting (isort's order-by-type): constants, classes, then the rest.
    kind = 0 if name.isupper() and len(name) > 1 else 1 if name[:1].isupper() else 2
    return kind, name.lower(), name


def stub(where: dict[str, tuple[str, ...]]) -> str:
    """The text of `__init__.pyi` for `_MODULES` = `where`."""
    lines = [HEADER]
    for module in sorted(where):
        names = sorted(where[module], key=_order)
        one = f"from .{module} import {', '.join(f'{n} as {n}' for n in names)}"
        if len(names) == 1 and len(one) <= LINE_MAX:
            lines.append(one)
        else:
            lines += [f"from .{module} import (", *(f"    {n} as {n}," for n in names), ")"]
    every = sorted(n for names in where.values() for n in names)
    lines += ["", "__version__: str", "", "__all__ = [", *(f'    "{n}",' for n in every), "]"]
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    path = PACKAGE / "__init__.pyi"
    text = stub(modules())
    if argv == ["--check"]:
        if not path.is_file() or path.read_text() != text:
            print(f"{path} is not what tools/make_stub.py writes from _MODULES: rerun it",
                  file=sys.stderr)  # fmt: skip
            return 1
        return 0
    if argv:
        raise SystemExit(__doc__.split("\n\n")[1])
    path.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
