"""The `jaxlens` command. Parses, validates, and calls the public functions."""

import argparse
import importlib
import sys

# Each subcommand lives in a module with `register(subparsers)`; the handler it sets
# with `set_defaults(run=...)` returns the exit code.
_COMMANDS = ("jaxlens._cli_render",)
_OPTIONAL = ("jaxlens._cli_fit",)


class UsageError(Exception):
    """Bad input from the command line: one line on stderr, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxlens", description="Gravitational lensing by a Schwarzschild black hole."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMANDS:
        importlib.import_module(name).register(sub)
    for name in _OPTIONAL:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name != name:
                raise
            continue
        mod.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (UsageError, ValueError, OSError) as e:
        print(f"jaxlens {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"jaxlens {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
