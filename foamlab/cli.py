"""`foamlab` command line: one subcommand per module in foamlab/commands/.

Each module defines ``register(subparsers)`` which adds its parser and sets
``func`` (args -> exit code). Errors the user can act on are FoamlabError and
are printed as one line; nothing ever ends in a traceback for bad input.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from foamlab import FoamlabError, __version__

# Order here is the order in `foamlab --help`.
COMMAND_MODULES = ["run", "probe", "sim", "fit", "diagnose", "batch", "report", "series", "gui", "show", "catalog"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="foamlab",
        description="Compression testing of flexible foam: run, simulate, fit, diagnose.",
    )
    parser.add_argument("--version", action="version", version=f"foamlab {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"foamlab.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"foamlab.commands.{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    for subparser in [parser, *sub.choices.values()]:   # the top parser reports unknown options
        subparser.error = _one_line_error(subparser)
    return parser


def _one_line_error(parser: argparse.ArgumentParser):
    """Bad arguments: one line and exit 2, not a usage block (every subcommand)."""
    def error(message: str):
        print(f"{parser.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)
    return error


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except FoamlabError as exc:
        print(f"foamlab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"foamlab {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
