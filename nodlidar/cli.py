"""The ``nodlidar`` command line.

Subcommands live in :mod:`nodlidar.commands` (one module each, discovered here). Errors
the user can fix (:class:`~nodlidar.errors.NodlidarError`) become one line on stderr and
exit status 2; what the system refuses (``OSError``: a serial port that does not exist or is
busy, a full disk) one line and exit status 1. Nothing the user typed produces a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
import textwrap
from typing import NoReturn

from . import commands
from .commands._output import (
    catch_swallowed_interrupts,
    configure,
    interrupted_teardown,
    paragraphs,
    plain,
    raise_if_interrupted,
)
from .errors import NodlidarError

__all__ = ["main", "build_parser", "EXIT_CODES"]

EXIT_OK = 0
EXIT_OS = 1  # the system refused (device missing, port busy, disk full)
EXIT_USAGE = 2  # the user can fix the input (also: no command given)
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)

#: The exit statuses, as ``nodlidar --help`` and docs/cli.md list them.
EXIT_CODES = (
    (EXIT_OK, "success"),
    (EXIT_OS, "the system refused: a device or port that is missing or busy, a full disk"),
    (EXIT_USAGE, "bad input the user can fix (option, file, value); also no command given "
                 "(the help is printed)"),
    (EXIT_INTERRUPTED, "interrupted (Ctrl-C)"),
)

_EPILOG = ("-q and -v go before or after the command (nodlidar -q scan). Every command has "
           "--help.\n\nexit status:\n" + "\n".join(f"- {c}: {t}" for c, t in EXIT_CODES))


class _Formatter(argparse.HelpFormatter):
    """Descriptions and epilogs: plain text (no reST markup), paragraphs and bullet items
    kept, each refilled to the terminal width."""

    def _fill_text(self, text, width, indent):
        out = []
        for items in paragraphs(plain(text) or ""):
            for item in items:
                hang = "  " if item[:2] in ("- ", "* ") else ""   # bullet text hangs under itself
                out.append(textwrap.fill(item, width, initial_indent=indent,
                                         subsequent_indent=indent + hang))
            out.append("")
        return "\n".join(out).rstrip("\n")


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line (no usage dump) and exit 2; help is plain."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:  # noqa: D401
        self.exit(EXIT_USAGE, f"{self.prog}: {message}\n")


def _add_global_flags(p: argparse.ArgumentParser, default) -> None:
    g = p.add_argument_group("global options")
    g.add_argument("-q", "--quiet", action="count", default=default,
                   help="no status lines or progress bars (stderr); results and errors only")
    g.add_argument("-v", "--verbose", action="count", default=default,
                   help="more detail on stderr (debug log)")


def _plain_help(p: argparse.ArgumentParser) -> None:
    """Strip reST markup from a command's description and option help texts."""
    p.description = plain(p.description)
    p.epilog = plain(p.epilog)
    for a in p._actions:
        if isinstance(a.help, str):
            a.help = plain(a.help)
    for g in p._action_groups:
        g.description = plain(g.description)


class _VersionAction(argparse.Action):
    """``--version``: prints ``nodlidar X.Y.Z`` and exits, as argparse's own; the version is
    looked up only when asked (importlib.metadata would cost every start-up ~40 ms)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS,
                 help: str = "show program's version number and exit") -> None:
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> NoReturn:
        from . import __version__

        parser._print_message(f"nodlidar {__version__}\n", sys.stdout)
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="nodlidar", epilog=_EPILOG,
                     description="Design workbench and runtime for a nodding 2D lidar with "
                                 "reconfigurable mirrors.")
    parser.add_argument("--version", action=_VersionAction)
    _add_global_flags(parser, 0)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    for p in sub.choices.values():
        _plain_help(p)
        # also after the command (nodlidar scan -q); SUPPRESS keeps the global value
        if not any(o in p._option_string_actions for o in ("-q", "--quiet", "-v", "--verbose")):
            _add_global_flags(p, argparse.SUPPRESS)
    for a in sub._choices_actions:   # the one-line help in the command list
        a.help = plain(a.help)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status (testable in process)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:   # bare `nodlidar`: the help, on stdout, and the usage status
        parser.print_help()
        return EXIT_USAGE
    configure(int(args.verbose or 0) - int(args.quiet or 0))
    log = logging.getLogger("nodlidar")
    if log.isEnabledFor(logging.DEBUG):  # the version lookup costs ~40 ms: only when shown
        from . import __version__

        log.debug("nodlidar %s, Python %s, %s", __version__, sys.version.split()[0],
                  {k: v for k, v in vars(args).items() if not callable(v)})
    restore_hook = catch_swallowed_interrupts()
    try:
        code = int(args.func(args) or 0)
        raise_if_interrupted()   # never report success for a run the user cancelled
        return code
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
        interrupted_teardown()  # what the Ctrl-C left half built fails quietly
        print(f"nodlidar {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        restore_hook()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
