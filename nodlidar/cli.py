"""The ``nodlidar`` command line.

Subcommands live in :mod:`nodlidar.commands` (one module each, discovered here). Errors
the user can fix (:class:`~nodlidar.errors.NodlidarError`) become one line on stderr and
exit status 2; what the system refuses (``OSError``: a serial port that does not exist or is
busy, a full disk) one line and exit status 1. Nothing the user typed produces a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from . import commands
from .errors import NodlidarError

EXIT_USAGE = 2  # the user can fix the input
EXIT_OS = 1  # the system refused (device missing, port busy, disk full)


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line (no usage dump) and exit 2."""

    def error(self, message: str) -> None:  # noqa: D401
        self.exit(EXIT_USAGE, f"{self.prog}: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="nodlidar", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status (testable in process)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except NodlidarError as exc:
        print(f"nodlidar {args.command}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # e.g. `nodlidar design x.toml --json | head`
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # a port that cannot be opened, a full disk: the system's words, one line
        print(f"nodlidar {args.command}: {exc}", file=sys.stderr)
        return EXIT_OS
    except KeyboardInterrupt:
        print(f"nodlidar {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
