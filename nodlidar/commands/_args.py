"""Argument checks shared by every command: bounded numbers, output paths, safe names.

- :func:`bounded_float` / :func:`bounded_int` are argparse ``type=`` factories: a value
  that is not finite or not within ``lo .. hi`` is a usage error naming the option and the
  allowed range (argparse prefixes ``argument --opt:``), before any work starts.
- :func:`check_output_path` is the one overwrite policy: an existing output is refused
  unless ``--force`` (:func:`add_force_arg`), and the parent directory must exist and be
  writable; call it before any long work.
- :func:`safe_name` keeps a name (e.g. a design's) from escaping the output folder.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

from ..errors import ParameterError
from ..validation import safe_name

__all__ = ["bounded_float", "bounded_int", "finite_float", "add_force_arg", "check_output_path",
           "safe_name"]


def _fmt(x: float) -> str:
    """Bounds as the user would type them: 2000000, not 2e+06."""
    if float(x).is_integer() and abs(x) < 1e19:
        return str(int(x))
    return f"{x:g}"


def _range(lo, hi, lo_open: bool, unit: str) -> str:
    u = f" {unit}" if unit else ""
    if lo is None and hi is None:
        return ""
    if hi is None:
        return f" {'>' if lo_open else '>='} {_fmt(lo)}{u}"
    if lo is None:
        return f" <= {_fmt(hi)}{u}"
    return f" in {_fmt(lo)}{' (excluded)' if lo_open else ''} .. {_fmt(hi)}{u}"


def _to_float(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def bounded_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                  unit: str = "") -> Callable[[str], float]:
    """argparse ``type=``: a finite float within ``lo .. hi`` (``lo_open``: ``> lo``)."""
    allowed = "a finite number" + _range(lo, hi, lo_open, unit)

    def parse(text: str) -> float:
        v = _to_float(text)
        if v is None:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number; allowed: {allowed}")
        ok = math.isfinite(v) and (lo is None or (v > lo if lo_open else v >= lo)) and (
            hi is None or v <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"{text} is out of range; allowed: {allowed}")
        return v

    parse.__name__ = "number"  # argparse names the type in some messages
    return parse


def finite_float(text: str) -> float:
    """argparse ``type=``: any finite float."""
    return bounded_float()(text)


def bounded_int(lo: int | None = None, hi: int | None = None, *,
                unit: str = "") -> Callable[[str], int]:
    """argparse ``type=``: an integer within ``lo .. hi`` (``1e5`` is read as 100000)."""
    allowed = "an integer" + _range(lo, hi, False, unit)

    def parse(text: str) -> int:
        f = _to_float(text)
        if f is None or not (math.isfinite(f) and f.is_integer()):
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer; allowed: {allowed}")
        try:
            v = int(text)  # exact for long integers
        except ValueError:
            v = int(f)     # 1e5
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{text} is out of range; allowed: {allowed}")
        return v

    parse.__name__ = "integer"
    return parse


def add_force_arg(p: argparse.ArgumentParser) -> None:
    """``--force``: overwrite an existing output (the one policy of every command)."""
    p.add_argument("--force", action="store_true", help="overwrite an existing output")


def check_output_path(path: str | os.PathLike, *, force: bool, kind: str = "file",
                      option: str = "--out") -> Path:
    """Check an output path before any long work.

    Parameters
    ----------
    path : path-like
        What the user gave.
    force : bool
        Overwrite an existing output (``--force``); without it an existing path is refused.
    kind : ``"file"`` or ``"directory"``
        What the command writes there.
    option : str
        The option, for messages.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ParameterError
        The parent directory does not exist, is not a directory or is not writable; the
        path exists and is the wrong kind (a directory where a file is expected, or the
        other way round); or it exists and ``force`` is false.
    """
    if kind not in ("file", "directory"):
        raise ValueError(f"kind must be 'file' or 'directory', got {kind!r}")
    p = Path(path)
    if str(path) == "" or "\x00" in str(path):
        raise ParameterError(option, str(path), f"a {kind} path")
    if p.exists() or p.is_symlink():
        if kind == "file" and p.is_dir():
            raise ParameterError(option, str(path), "a file name, not an existing directory")
        if kind == "directory" and not p.is_dir():
            raise ParameterError(option, str(path), "a directory, not an existing file")
        if not force:
            raise ParameterError(option, str(path),
                                 f"a {kind} that does not exist yet (or --force to overwrite it)")
        if not os.access(p, os.W_OK):
            raise ParameterError(option, str(path), f"a writable {kind}")
        return p
    parent = p.absolute().parent
    if not parent.exists():
        raise ParameterError(option, str(path), f"a path in an existing directory ({parent} "
                                                "does not exist)")
    if not parent.is_dir():
        raise ParameterError(option, str(path), f"a path in a directory ({parent} is a file)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ParameterError(option, str(path), f"a path in a writable directory ({parent} is "
                                                "not writable)")
    return p
