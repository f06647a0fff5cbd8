"""JSON as matscan reads and writes it: strict, finite, and named in every error.

Writing: :func:`dumps` refuses NaN and infinities (they are not JSON; a file with a
bare ``NaN`` breaks every other reader) and names the field that held one.

Reading: :func:`read_json` (files) and :func:`loads_text` (JSON held in a string)
refuse what other readers would read differently or what would break matscan later
(non-UTF-8, NaN, 1e400, huge integers, deep nesting, huge files); the ``check_*``
helpers check one field each, with messages naming the file and the field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from matscan.errors import MatscanError


def _first_non_finite(obj: Any, where: str = "") -> str | None:
    """The path (``a.b[2]``) of the first NaN or infinite float in ``obj``, or None."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else (where or "value")
    if isinstance(obj, dict):
        for k, v in obj.items():
            found = _first_non_finite(v, f"{where}.{k}" if where else str(k))
            if found:
                return found
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            found = _first_non_finite(v, f"{where}[{i}]")
            if found:
                return found
    return None


def finite_or_null(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float replaced by None (JSON null): for
    tables of scores, where "not defined" is a value, not an error."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    return obj


def dumps(obj: Any, what: str = "JSON", indent: int | None = 2) -> str:
    """``obj`` as JSON text (with a final newline), refusing non-finite numbers.

    ``what`` names the document in the error (a file name).
    """
    try:
        return json.dumps(obj, indent=indent, allow_nan=False) + "\n"
    except ValueError:
        field = _first_non_finite(obj)
        raise MatscanError(f"{what}: {field} is not a finite number; nothing was written") from None


# --- reading ---------------------------------------------------------------------------
#
# Reading: :func:`read_json` and :func:`loads_text` are the one way matscan parses JSON.
# They accept only what every other JSON reader reads the same way: strict UTF-8, no
# ``NaN``/``Infinity``, numbers that are finite as floats and integers of at most
# ``MAX_INT``, nesting of at most ``MAX_DEPTH`` levels, no key twice in one object, and
# files of at most ``MAX_BYTES``. Every refusal is a one-line :class:`MatscanError`
# naming the file (and, for a bad number, the field that held it).
#
# The ``check_*`` helpers then check one field each; ``where`` names the file and the
# field (``capture.json: images[3].intensity``) and starts the message.

#: The largest JSON file matscan reads (capture, rig, calibration and map set files
#: are a few kilobytes; a rig with thousands of lights is under a megabyte).
MAX_BYTES = 16 * 2**20
#: The deepest nesting of lists and objects (matscan's own files go 5 deep).
MAX_DEPTH = 32
#: The largest integer magnitude: every integer up to it is exact as a float too.
MAX_INT = 2**53


class _Bad:
    """A value the parser refused, kept in place so the walk can name its field."""

    def __init__(self, problem: str) -> None:
        self.problem = problem


class _Refused(Exception):
    """Raised inside the parser for a refusal that has no field (a repeated key)."""


def _parse_int(text: str) -> int | _Bad:
    digits = text.lstrip("-")
    if len(digits) > 16 or int(text) > MAX_INT or int(text) < -MAX_INT:
        shown = text if len(text) <= 20 else f"{text[:12]}… ({len(digits)} digits)"
        return _Bad(f"the integer {shown} is too large (at most 2**53 in magnitude)")
    return int(text)


def _parse_float(text: str) -> float | _Bad:
    value = float(text)
    if not math.isfinite(value):
        shown = text if len(text) <= 20 else f"{text[:12]}… ({len(text)} characters)"
        return _Bad(f"the number {shown} is out of range (not a finite float)")
    return value


def _parse_constant(text: str) -> _Bad:
    return _Bad(f"{text} is not a number JSON allows (write a finite number)")


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _Refused(f"key {short_repr(key)} appears twice in one object")
        out[key] = value
    return out


def short_repr(value: Any, limit: int = 60) -> str:
    """A short one-line ``repr`` of a value for an error message."""
    try:
        text = repr(value)
    except ValueError:  # an int beyond Python's digit limit
        return "a very large integer"
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _printable(name: str) -> str:
    """``name`` with characters that would break a one-line message escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in name)


def _is_unicode(text: str) -> bool:
    """Whether ``text`` is valid Unicode (JSON's ``\\ud800`` escapes can make it otherwise)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _walk(obj: Any, what: str) -> None:
    """Refuse the first parser-marked value (naming its field) or too deep a nesting."""
    stack: list[tuple[Any, str, int]] = [(obj, "", 0)]
    while stack:
        value, path, depth = stack.pop()
        if isinstance(value, _Bad):
            raise MatscanError(f"{what}: {path or 'value'}: {value.problem}")
        if isinstance(value, str) and not _is_unicode(value):
            raise MatscanError(f"{what}: {path or 'value'}: holds an unpaired surrogate (\\uD800-\\uDFFF); not text")
        if isinstance(value, (dict, list)):
            if depth >= MAX_DEPTH:
                raise MatscanError(f"{what}: nested deeper than {MAX_DEPTH} levels")
            items = value.items() if isinstance(value, dict) else enumerate(value)
            children = []
            for key, child in items:
                if isinstance(key, str) and not _is_unicode(key):
                    raise MatscanError(f"{what}: {path or 'value'}: a key holds an unpaired surrogate; not text")
                sub = f"{path}[{key}]" if isinstance(key, int) else (f"{path}.{key}" if path else str(key))
                children.append((child, _printable(sub), depth + 1))
            stack.extend(reversed(children))


def loads_text(text: str, what: str) -> Any:
    """Parse JSON held in a string (``what`` names it in errors), as :func:`read_json` does.

    For JSON inside another container, e.g. the metadata of a safetensors file.
    """
    what = _printable(what)
    if not isinstance(text, str):
        raise MatscanError(f"{what}: expected JSON text, got {type(text).__name__}")
    if len(text) > MAX_BYTES:
        raise MatscanError(f"{what}: {len(text)} characters of JSON; at most {MAX_BYTES} are read")
    try:
        data = json.loads(
            text,
            parse_int=_parse_int,
            parse_float=_parse_float,
            parse_constant=_parse_constant,
            object_pairs_hook=_pairs,
        )
    except json.JSONDecodeError as exc:
        raise MatscanError(f"{what}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except RecursionError:
        raise MatscanError(f"{what}: nested deeper than {MAX_DEPTH} levels") from None
    except _Refused as exc:
        raise MatscanError(f"{what}: {exc}") from None
    _walk(data, what)
    return data


def read_json(path: str | Path, what: str | None = None) -> Any:
    """Read a JSON file strictly (see above); ``what`` names it in errors (default: the path).

    Errors, each one line naming the file: no such file, unreadable, larger than
    ``MAX_BYTES``, not UTF-8, not JSON, a non-finite or too large number (with its
    field), nesting deeper than ``MAX_DEPTH``, a key twice in one object.
    """
    path = Path(path)
    name = _printable(what if what is not None else str(path))
    try:
        special = path.exists() and not path.is_file()  # a folder, or a pipe that would block the read
    except ValueError:  # a path with a NUL character
        raise MatscanError(f"{name}: not a usable file name") from None
    except OSError as exc:  # a name too long, a folder that cannot be entered
        raise MatscanError(f"{name}: cannot read ({exc.strerror or type(exc).__name__})") from None
    if special:
        raise MatscanError(f"{name}: not a regular file")
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise MatscanError(f"{name}: no such file") from None
    except OSError as exc:
        raise MatscanError(f"{name}: cannot read ({exc.strerror or type(exc).__name__})") from None
    except ValueError:  # a path with a NUL character
        raise MatscanError(f"{name}: not a usable file name") from None
    if len(raw) > MAX_BYTES:
        raise MatscanError(f"{name}: larger than {MAX_BYTES // 2**20} MiB; not a matscan JSON file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise MatscanError(f"{name}: not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    return loads_text(text, name)


# --- field checks ---------------------------------------------------------------------


def _kind(value: Any) -> str:
    """The JSON name of a value's type, for messages."""
    if isinstance(value, bool):
        return "true/false"
    if value is None:
        return "null"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (list, tuple)):
        return "a list"
    if isinstance(value, Mapping):
        return "an object"
    return type(value).__name__


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _range_text(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f"from {low:g} to {high:g}"
    return f"at least {low:g}" if low is not None else f"at most {high:g}"


def check_number(
    value: Any, where: str, low: float | None = None, high: float | None = None, positive: bool = False
) -> float:
    """A finite number (int or float, not true/false), optionally > 0 and in [low, high]."""
    if not _is_number(value) or (isinstance(value, int) and abs(value) > MAX_INT) or not math.isfinite(value):
        raise MatscanError(f"{where}: expected a finite number, got {short_repr(value)}")
    if positive and value <= 0:
        raise MatscanError(f"{where}: must be positive, got {short_repr(value)}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise MatscanError(f"{where}: {short_repr(value)} is out of range ({_range_text(low, high)})")
    return float(value)


def check_int(value: Any, where: str, low: int | None = None, high: int | None = None) -> int:
    """An integer (not a float, not true/false) in [low, high]."""
    if not isinstance(value, int) or isinstance(value, bool) or abs(value) > MAX_INT:
        raise MatscanError(f"{where}: expected an integer, got {short_repr(value)}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise MatscanError(f"{where}: {value} is out of range ({_range_text(low, high)})")
    return value


def check_vector(
    value: Any, n: int, where: str, low: float | None = None, high: float | None = None
) -> tuple[float, ...]:
    """Exactly ``n`` finite numbers (a list), each in [low, high]."""
    if (
        not isinstance(value, (list, tuple))
        or len(value) != n
        or not all(_is_number(v) and abs(v) <= (MAX_INT if isinstance(v, int) else math.inf) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise MatscanError(f"{where}: expected {n} finite numbers, got {short_repr(value)}")
    for i, v in enumerate(value):
        if (low is not None and v < low) or (high is not None and v > high):
            raise MatscanError(f"{where}[{i}]: {short_repr(v)} is out of range ({_range_text(low, high)})")
    return tuple(float(v) for v in value)


def check_string(value: Any, where: str, choices: Sequence[str] | None = None) -> str:
    """A non-empty string of printable characters, one of ``choices`` when given."""
    if not isinstance(value, str) or not value:
        raise MatscanError(f"{where}: expected a non-empty string, got {short_repr(value)}")
    if choices is not None and value not in choices:
        raise MatscanError(f"{where}: {short_repr(value)} is not one of {', '.join(choices)}")
    if not value.isprintable():
        raise MatscanError(f"{where}: {short_repr(value)} holds control or unpaired characters")
    return value


def check_file_name(value: Any, where: str) -> str:
    """A file name (relative to the file that names it, or absolute): a printable string."""
    if not isinstance(value, str) or not value:
        raise MatscanError(f"{where}: expected a file name, got {short_repr(value)}")
    if not value.isprintable():
        raise MatscanError(f"{where}: {short_repr(value)} is not a usable file name (control or unpaired characters)")
    return value


def check_bool(value: Any, where: str) -> bool:
    """``true`` or ``false``."""
    if not isinstance(value, bool):
        raise MatscanError(f"{where}: expected true or false, got {short_repr(value)}")
    return value


def check_list(value: Any, where: str, what: str = "items", empty_ok: bool = False) -> list[Any]:
    """A list (non-empty unless ``empty_ok``); ``what`` says what it should hold."""
    if not isinstance(value, (list, tuple)) or (not value and not empty_ok):
        qualifier = "" if empty_ok else "non-empty "
        raise MatscanError(f"{where}: expected a {qualifier}list of {what}, got {short_repr(value)}")
    return list(value)


def check_object(value: Any, where: str, keys: Mapping[str, bool] | None = None) -> Mapping[str, Any]:
    """An object; with ``keys`` (name → required) no other key and every required one."""
    if not isinstance(value, Mapping):
        raise MatscanError(f"{where}: expected an object, got {_kind(value)}")
    if keys is not None:
        for key in value:
            if key not in keys:
                raise MatscanError(f"{where}: unknown key {short_repr(key)} (expected one of {', '.join(keys)})")
        for key, required in keys.items():
            if required and key not in value:
                raise MatscanError(f"{where}: missing field {key!r}")
    return value
