"""What the CLI shows besides results: status lines, progress bars, help text.

- Status and progress lines go through the ``nodlidar`` logger to stderr; ``-q`` hides
  them (and progress bars), ``-v`` adds debug detail (:func:`configure`).
- :func:`progress_disable` is the ``disable=`` every tqdm bar of the CLI passes: ``True``
  under ``-q``, else ``None`` (tqdm's own rule: drawn on a terminal only).
- :func:`plain` turns a docstring into the plain text ``--help`` shows (no reST markup).
- :func:`catch_swallowed_interrupts` / :func:`raise_if_interrupted`: a Ctrl-C that Python
  had to swallow still ends the command with status 130.
"""

from __future__ import annotations

import logging
import re
import sys
from collections.abc import Callable

__all__ = ["configure", "status", "progress_disable", "plain", "paragraphs", "LOGGER",
           "catch_swallowed_interrupts", "raise_if_interrupted", "interrupted_teardown"]

LOGGER = "nodlidar"


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (in-process callers swap it)."""

    def __init__(self) -> None:
        super().__init__()

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def configure(verbosity: int) -> None:
    """Route the ``nodlidar`` logger to stderr: ``verbosity`` < 0 warnings only (``-q``),
    0 status lines (default), > 0 debug (``-v``). Idempotent (one handler)."""
    log = logging.getLogger(LOGGER)
    if not any(isinstance(h, _StderrHandler) for h in log.handlers):
        h = _StderrHandler()
        h.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(h)
    log.setLevel(logging.WARNING if verbosity < 0 else logging.DEBUG if verbosity > 0 else logging.INFO)
    log.propagate = False


_swallowed_interrupt = False
_tearing_down = False  # interrupted_teardown: unraisable exceptions dropped


def catch_swallowed_interrupts() -> Callable[[], None]:
    """Remember a Ctrl-C that Python could not raise; returns the restorer.

    A ``KeyboardInterrupt`` raised where Python cannot propagate it (a ``gc`` callback such
    as Dask's ``GCDiagnosis``, a ``__del__``, a weakref callback) is printed as "Exception
    ignored in ..." and dropped: the command then ran to the end and exited 0 with the
    result the user had just cancelled. This hook records it instead (and prints nothing);
    :func:`raise_if_interrupted` raises it again at the next checkpoint (each progress
    update, and before the CLI reports success).
    """
    global _swallowed_interrupt, _tearing_down
    _swallowed_interrupt = _tearing_down = False
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        global _swallowed_interrupt
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _swallowed_interrupt = True
            return
        if _tearing_down:
            return  # an object the Ctrl-C left half built, failing in __del__: not news
        previous(unraisable)

    sys.unraisablehook = hook

    def restore() -> None:
        global _tearing_down
        if _tearing_down:
            import gc

            gc.collect()  # (reference cycles: their __del__ under the quiet hook too)
            _tearing_down = False
        sys.unraisablehook = previous

    return restore


def interrupted_teardown() -> None:
    """After a Ctrl-C: until the restorer of :func:`catch_swallowed_interrupts` runs (it
    also collects what the interrupted frames held), its hook drops every unraisable
    exception. A ``KeyboardInterrupt`` that lands inside a constructor (e.g. Dask's
    ``Future.__init__`` while the workers start) leaves an object whose ``__del__`` then
    fails ("Exception ignored in ... AttributeError"): noise under the one line that says
    what happened."""
    global _tearing_down
    _tearing_down = True


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if a Ctrl-C was swallowed (:func:`catch_swallowed_interrupts`)."""
    global _swallowed_interrupt
    if _swallowed_interrupt:
        _swallowed_interrupt = False
        raise KeyboardInterrupt


def status(msg: str) -> None:
    """One status line on stderr (hidden by ``-q``)."""
    log = logging.getLogger(LOGGER)
    if not log.handlers:   # run() called without nodlidar.cli.main: behave as before
        print(msg, file=sys.stderr, flush=True)
        return
    log.info(msg)


def progress_disable() -> bool | None:
    """tqdm's ``disable=``: ``True`` under ``-q``, else ``None`` (only on a terminal)."""
    log = logging.getLogger(LOGGER)
    return True if log.handlers and not log.isEnabledFor(logging.INFO) else None


_ROLE = re.compile(r":(?:py:)?[a-z]+:`(~?)([^`<]*?)(?:\s*<([^`>]*)>)?`")
_LITERAL = re.compile(r"``(.+?)``", re.S)  # a literal may span a line break
_ITEM = re.compile(r"^\s*(?:[-*]|\d+\.)\s")


def _role(m: re.Match) -> str:
    tilde, text, target = m.group(1), m.group(2).strip(), m.group(3)
    if target:            # :func:`title <target>` -> title
        return text
    return text.rsplit(".", 1)[-1] if tilde else text


def plain(text: str | None) -> str | None:
    """``text`` without reST markup: ``:role:`~a.b``` -> ``b``, ````x```` -> ``x``, and
    ``a.b()`` roles keep their text. Paragraphs (blank lines) are kept."""
    if text is None:
        return None
    return _LITERAL.sub(r"\1", _ROLE.sub(_role, text))


def paragraphs(text: str) -> list[list[str]]:
    """``text`` split into paragraphs, each a list of items (a bullet list item starts a new
    one), each item's lines joined with single spaces."""
    import inspect

    out: list[list[str]] = []
    for block in re.split(r"\n\s*\n", inspect.cleandoc(text)):
        items: list[str] = []
        for line in block.splitlines():
            if not items or _ITEM.match(line):
                items.append(line.strip())
            else:
                items[-1] += " " + line.strip()
        if items:
            out.append(items)
    return out
