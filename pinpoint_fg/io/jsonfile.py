"""Reading JSON files defensively: one function, :func:`load_json`, for every JSON input.

Python's ``json`` recurses once per nesting level (a file of 100 000 ``[`` raises
``RecursionError``) and turns any digit string into an ``int`` (a 5000-digit integer raises
``ValueError`` from the int-size limit; one of 4000 digits overflows the first ``float()``).
:func:`load_json` checks the nesting depth with a flat scan before parsing, refuses integer
literals longer than :data:`MAX_INT_DIGITS` digits, and reports every problem, reading errors
included, as one :class:`~pinpoint_fg.errors.InputError` naming the file.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from pinpoint_fg.errors import InputError

#: Deepest accepted nesting of arrays/objects (the project's files use 3).
MAX_JSON_DEPTH = 64
#: Longest accepted integer literal, digits: int64's 19 (a ROS time stamp in ns has 19); a literal of
#: 19 digits must still fit in int64.
MAX_INT_DIGITS = 19
#: Largest integer the project's JSON files hold (int64): also the largest seed a result can record.
INT64_MAX = 2**63 - 1

#: The characters the nesting scan stops at: brackets, and what starts, ends or escapes a string.
_SPECIAL = re.compile(r'[\[\]{}"\\]')


def json_shown(v: Any, limit: int = 60) -> str:
    """A JSON value as text for an error message, shortened to ``limit`` characters."""
    text = json.dumps(v)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def json_depth(text: str) -> int:
    """Largest nesting depth of ``[``/``{`` in ``text`` (brackets inside strings ignored), without recursion.

    A scan over the special characters only (:data:`_SPECIAL`), with JSON's string rules: a ``"`` opens a string,
    a ``\\`` inside one escapes the next character, the next unescaped ``"`` closes it; an unterminated string runs
    to the end, as ``json.loads`` reads it. Linear in the text and no memory per character: a regular expression
    for whole strings kept a backtracking frame per character (6 GB for a 50 MB string) and was quadratic on an
    unterminated string of escapes.
    """
    depth = deepest = 0
    in_string = False
    escaped = -1  # the position a backslash escapes
    for m in _SPECIAL.finditer(text):
        i = m.start()
        if i == escaped:
            continue
        c = text[i]
        if in_string:
            if c == "\\":
                escaped = i + 1
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    return deepest


class _IntTooLong(ValueError):
    pass


def _parse_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise _IntTooLong(f"integer literal with {digits} digits (at most {MAX_INT_DIGITS} accepted)")
    value = int(text)
    if not -INT64_MAX - 1 <= value <= INT64_MAX:
        raise _IntTooLong(f"integer literal {text} does not fit in int64")
    return value


def loads_json(text: str, file: str | Path) -> Any:
    """Parse ``text`` (the contents of ``file``) within the limits above; :class:`InputError` otherwise."""
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise InputError(f"JSON nested {depth} levels deep (at most {MAX_JSON_DEPTH} accepted)", file=file)
    try:
        return json.loads(text, parse_int=_parse_int)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}", file=file) from None
    except _IntTooLong as exc:
        raise InputError(str(exc), file=file) from None
    except (ValueError, RecursionError) as exc:  # belt and braces: no parser error escapes as a traceback
        raise InputError(f"not valid JSON: {exc}", file=file) from None


def load_json(path: str | Path, missing: str = "file not found") -> Any:
    """Read and parse the JSON file ``path``; :class:`InputError` (``missing`` when it does not exist)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(missing, file=path) from None
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text: {exc.reason} at byte {exc.start}", file=path) from None
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InputError(f"cannot read: {why}", file=path) from None
    return loads_json(text, path)
