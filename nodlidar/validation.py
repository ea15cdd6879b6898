"""One validation layer for every input: files, TOML tables, typed fields and numbers.

Everything here raises a typed :mod:`nodlidar.errors` exception whose message is one line
naming the file (when there is one), the parameter, the value and what is allowed, so the
CLI prints it as ``nodlidar <command>: <message>``.

- :func:`read_toml` reads a TOML input file, refusing what is not a small regular UTF-8
  text file (a FIFO would block forever, a huge file would exhaust memory).
- :func:`check_keys` refuses unknown sections or keys, suggesting the nearest valid name.
- :func:`check_fields` converts a table to a dataclass's keyword arguments with strict
  types taken from its annotations: no ``true`` for a number, no ``"false"`` for a boolean,
  finite numbers only, tuples of the right length.
- :func:`check_number` bounds one number (finite, ``lo .. hi``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import stat
import tomllib
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

from .errors import InputFileError, NodlidarError, ParameterError, UnknownKeyError

__all__ = [
    "MAX_TOML_BYTES",
    "read_toml",
    "suggest",
    "check_keys",
    "check_fields",
    "check_value",
    "check_number",
    "safe_name",
]

#: Largest TOML input read [bytes]. The design files are ~4 kB and scenes a few kB; 4 MiB
#: leaves room for generated files while refusing a mistaken multi-GB path.
MAX_TOML_BYTES = 4 << 20


def _in(source: str | None) -> str:
    return f" in {source}" if source else ""


def read_toml(path: str | os.PathLike, what: str, *, max_bytes: int = MAX_TOML_BYTES,
              error: type[NodlidarError] = InputFileError) -> dict[str, Any]:
    """Read and parse a TOML input file.

    Parameters
    ----------
    path : path-like
        The file the user gave.
    what : str
        What the file should be, for messages (``"design"``, ``"scene"``, ``"calibration"``).
    max_bytes : int
        Refuse larger files.
    error : NodlidarError subclass
        Raised for every refusal (default :class:`~nodlidar.errors.InputFileError`); the
        message always names the file.

    Raises
    ------
    error
        The file does not exist, is not a regular file (directory, FIFO, device, socket),
        is larger than ``max_bytes``, is not UTF-8, contains a NUL character, or is not
        valid TOML.
    """
    p = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO for reading must not wait for a writer; checked on the
        # open descriptor (fstat), so the file cannot be swapped after the check.
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise error(f"{what} file not found: {p}") from None
    except IsADirectoryError:
        raise error(f"{what} file {p} is a directory, not a file") from None
    except OSError as exc:
        raise error(f"{what} file {p} cannot be read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise error(f"{what} file {p} is a directory, not a file")
        if not stat.S_ISREG(st.st_mode):
            kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode) else
                    "a socket" if stat.S_ISSOCK(st.st_mode) else "a device")
            raise error(f"{what} file {p} is {kind}, not a regular file")
        if st.st_size > max_bytes:
            raise error(f"{what} file {p} is {st.st_size} bytes; allowed: at most {max_bytes} "
                        f"bytes")
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=False) as f:
            raw = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{what} file {p} cannot be read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(raw) > max_bytes:  # grew after the stat
        raise error(f"{what} file {p} is larger than {max_bytes} bytes")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise error(f"{what} file {p} is not UTF-8 text (byte 0x{raw[exc.start]:02x} on line "
                    f"{line})") from None
    if "\x00" in text:
        line = text[:text.index("\x00")].count("\n") + 1
        raise error(f"{what} file {p} contains a NUL character (line {line}); not a text file")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: malformed TOML: {exc}") from None


def suggest(name: str, choices: Iterable[str]) -> str | None:
    """The valid name nearest to ``name`` (difflib ratio >= 0.6), or None."""
    close = difflib.get_close_matches(str(name), list(choices), n=1, cutoff=0.6)
    return close[0] if close else None


def check_keys(table: Any, allowed: Iterable[str], where: str, source: str | None = None, *,
               sections: bool = False) -> dict[str, Any]:
    """Refuse a non-table or keys outside ``allowed``.

    Parameters
    ----------
    table : Any
        The parsed TOML value that should be a table.
    allowed : iterable of str
        The valid keys.
    where : str
        Dotted name of the table (``"placement"``, ``"tolerance.lidar"``; ``""`` for the
        top level).
    source : str, optional
        The file, for messages.
    sections : bool
        Tables among the keys are sections (messages say ``section [x]``); other keys
        are ``key a.x`` (``top-level key x`` at the top level).

    Returns
    -------
    dict
        ``table``, checked.

    Raises
    ------
    ParameterError
        ``table`` is not a table.
    UnknownKeyError
        With the nearest valid name (``did you mean ...?``) or the list of valid names.
    """
    allowed = sorted(set(allowed))
    if not isinstance(table, Mapping):
        raise ParameterError(where or "top level", table, "a table" + _in(source))
    for key in table:
        if key in allowed:
            continue
        dotted = f"{where}.{key}" if where else str(key)
        near = suggest(key, allowed)
        if sections and isinstance(table[key], Mapping):
            name, fmt = f"[{dotted}]", (lambda k: f"[{where + '.' if where else ''}{k}]")
            kind = "section"
        elif sections and not where:
            name, fmt, kind = dotted, str, "top-level key"
        else:
            name, fmt, kind = dotted, (lambda k: f"{where + '.' if where else ''}{k}"), "key"
        hint = (f"did you mean {fmt(near)}?" if near else
                "allowed: " + (", ".join(fmt(k) for k in allowed) or "none"))
        raise UnknownKeyError(f"unknown {kind} {name}{_in(source)}; {hint}", dotted, table[key],
                              ", ".join(allowed))
    return dict(table)


def check_number(value: Any, name: str, *, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False, integer: bool = False, unit: str = "",
                 source: str | None = None) -> float | int:
    """A finite number (not a boolean) within ``lo .. hi``.

    ``lo_open``: the lower bound itself is refused (``> lo``). ``integer``: a whole number
    (``3.0`` is accepted as 3). Returns a float (or int with ``integer``).
    """
    u = f" {unit}" if unit else ""
    kind = "an integer" if integer else "a finite number"
    rng = (f" {'>' if lo_open else '>='} {lo:g}{u}" if hi is None and lo is not None else
           f" <= {hi:g}{u}" if lo is None and hi is not None else
           f" in {lo:g}{' (excluded)' if lo_open else ''} .. {hi:g}{u}" if lo is not None
           and hi is not None else "")
    allowed = kind + rng + _in(source)
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok and integer:
        ok = float(value).is_integer()
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if not ok:
        raise ParameterError(name, value, allowed)
    return int(value) if integer else float(value)


def _range_text(lo: float | None, hi: float | None, unit: str) -> str:
    u = f" {unit}" if unit else ""
    if lo is None:
        return f"<= {hi:g}{u}"
    if hi is None:
        return f">= {lo:g}{u}"
    return f"{lo:g} .. {hi:g}{u}"


def _type_name(tp: Any) -> str:
    return {float: "a finite number", int: "an integer", bool: "true or false",
            str: "a string"}.get(tp, getattr(tp, "__name__", str(tp)))


def check_value(value: Any, tp: Any, name: str, source: str | None = None) -> Any:
    """``value`` checked against the type annotation ``tp`` and converted.

    ``float``: a finite int or float, not a boolean. ``int``: an integer, not a boolean.
    ``bool``: a boolean only (``"false"`` is refused). ``str``: a string without NUL.
    ``tuple[X, ...]``: a list of any length (a single value is taken as one-element; the
    dataclass checks the length);
    ``tuple[X, Y, Z]``: a list of exactly that length. ``dict``/``list``: that container.
    ``X | None``: None or X. A dataclass: a table checked by :func:`check_fields` and
    built (so nested tables get the same checks). Other annotations pass unchecked.
    """
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return check_value(value, inner[0], name, source)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ParameterError(name, value, "a finite number (not a string or true/false)"
                                 + _in(source))
        if not math.isfinite(value):
            raise ParameterError(name, value, "a finite number" + _in(source))
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParameterError(name, value, "an integer (not a string or true/false)"
                                 + _in(source))
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ParameterError(name, value, "true or false (a TOML boolean, not a string "
                                 "or number)" + _in(source))
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ParameterError(name, value, "a string" + _in(source))
        if "\x00" in value or any(ord(c) < 32 and c not in "\t\n" for c in value):
            raise ParameterError(name, value, "a string without control characters"
                                 + _in(source))
        return value
    if origin is tuple:
        if args and len(args) == 2 and args[1] is Ellipsis:
            items = list(value) if isinstance(value, list | tuple) else [value]
            return tuple(check_value(x, args[0], f"{name}[{i}]", source)
                         for i, x in enumerate(items))
        if not isinstance(value, list | tuple) or (args and len(value) != len(args)):
            what = f"a list of {len(args)} values" if args else "a list"
            raise ParameterError(name, value, what + _in(source))
        if not args:
            return tuple(value)
        return tuple(check_value(x, a, f"{name}[{i}]", source)
                     for i, (x, a) in enumerate(zip(value, args, strict=True)))
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        # a nested table ([[placement.mirrors]]): the same strict checks, field by field
        if isinstance(value, tp):
            return value
        return tp(**check_fields(tp, value, name, source))
    if tp is dict or origin is dict:
        if not isinstance(value, Mapping):
            raise ParameterError(name, value, "a table" + _in(source))
        return dict(value)
    if tp is list or origin is list:
        if not isinstance(value, list | tuple):
            raise ParameterError(name, value, "a list" + _in(source))
        if args:
            return [check_value(x, args[0], f"{name}[{i}]", source) for i, x in enumerate(value)]
        return list(value)
    return value


def check_fields(cls: type, table: Any, where: str, source: str | None = None, *,
                 bounds: Mapping[str, tuple] | None = None) -> dict[str, Any]:
    """Keyword arguments for dataclass ``cls`` from a TOML table, strictly checked.

    Parameters
    ----------
    cls : dataclass type
        Its field annotations give the types (see :func:`check_value`).
    table : Any
        The parsed table.
    where : str
        The table's dotted name, for messages (``"placement"``).
    source : str, optional
        The file, for messages.
    bounds : mapping, optional
        ``field -> (lo, hi, unit)``: physical bounds of number fields (each element of a
        tuple field); ``None`` for an open side.

    Returns
    -------
    dict
        Converted values of the keys present (absent keys keep the dataclass default).

    Raises
    ------
    UnknownKeyError, ParameterError, DesignFileError
        Unknown key (with the nearest valid one), wrong type, out of bounds, or a required
        field missing.
    """
    flds = [f for f in fields(cls) if f.init]
    table = check_keys(table, [f.name for f in flds], where, source)
    hints = typing.get_type_hints(cls)
    missing = [f.name for f in flds if f.name not in table and f.default is MISSING
               and f.default_factory is MISSING]
    if missing:
        from .errors import DesignFileError

        raise DesignFileError(f"[{where}] is incomplete{_in(source)}: missing "
                              f"{', '.join(missing)}")
    out: dict[str, Any] = {}
    for key, val in table.items():
        name = f"{where}.{key}" if where else key
        v = check_value(val, hints.get(key, Any), name, source)
        if bounds and key in bounds:
            lo, hi, unit = bounds[key]
            for x in (v if isinstance(v, tuple) else (v,)):
                if lo is not None and x < lo or hi is not None and x > hi:
                    raise ParameterError(name, val, _range_text(lo, hi, unit) + _in(source))
        out[key] = v
    return out


def safe_name(name: str, field: str = "name") -> str:
    """``name`` if it is safe as one path component inside an output folder.

    Refused: empty, ``.``/``..``, path separators, NUL or other control characters, a
    leading ``-`` or whitespace at either end.
    """
    ok = (isinstance(name, str) and name.strip() == name and name not in ("", ".", "..")
          and not any(c in name for c in "/\\") and not name.startswith("-")
          and not any(ord(c) < 32 or ord(c) == 127 for c in name))
    if not ok:
        raise ParameterError(field, name, "a name usable as a folder name: not empty, '.' or "
                                          "'..', no '/', '\\\\', control characters or leading '-'")
    return name
