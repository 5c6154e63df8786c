"""The ``osteonav`` command line.

Every module in :mod:`app.commands` that defines ``register(subparsers)`` adds one subcommand;
``register`` adds its parser and sets ``func`` (called with the parsed arguments, returning an exit
code). Command modules keep heavy imports (moderngl, rerun, OpenCV) inside their functions so that
``osteonav --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

import app.commands
from app.errors import OsteonavError
from app.outputs import close_all

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="osteonav",
        description="Markerless iliac crest tracking and AR osteotomy navigation.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(app.commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"app.commands.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
    for sub in _subparsers(parser):   # -v after the subcommand too (the top level's default stands)
        sub.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="debug logging")
    return parser


def _subparsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every subcommand's parser, nested ones (``calibrate hand-eye``) included, each once."""
    found: dict[int, argparse.ArgumentParser] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                if id(sub) not in found:
                    found[id(sub)] = sub
                    found.update((id(p), p) for p in _subparsers(sub))
    return list(found.values())


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:   # --help (0) or a refused option (2: usage and one error line already printed)
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (OsteonavError, OSError) as exc:   # OSError: a file system refusal the commands did not foresee
        print(f"osteonav {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"osteonav {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        close_all()   # the output folders' locks (app/outputs.py); their manifests stay


if __name__ == "__main__":
    sys.exit(main())
