"""Strict, bounded parsing of the bytes raytun3r reads from files it did not write itself.

Every function here either returns a value of the documented type or raises
:class:`~raytun3r_plugin.errors.Raytun3rError` (the subclass the caller passes), in time and
memory bounded by the input's size, for any input: no ``RecursionError`` from deep nesting, no
``ValueError`` from Python's limit on integer digits, no ``OverflowError``, and error messages
that quote at most :data:`QUOTE_CHARS` characters of the offending value.

The safetensors reader parses the header itself instead of trusting the library's lenient one:
the library keeps the last of two tensors with the same name and accepts any metadata, which a
shared adapter file must not get away with.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from raytun3r_plugin.errors import Raytun3rError

#: The most characters of a bad value that an error message quotes.
QUOTE_CHARS = 60
#: JSON objects and arrays nested deeper than this are refused before they are parsed.
MAX_JSON_DEPTH = 32

_INTEGER = re.compile(r"(0|-?[1-9][0-9]{0,17})")
# The safetensors dtype names that raytun3r's files may hold, and their element sizes.
_DTYPES = {
    "F32": (torch.float32, 4),
    "F16": (torch.float16, 2),
    "BF16": (torch.bfloat16, 2),
    "F64": (torch.float64, 8),
    "I64": (torch.int64, 8),
    "I32": (torch.int32, 4),
}


def quote(value: Any, limit: int = QUOTE_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters, never building a huge string: long strings
    are cut before ``repr``, containers and integers of hundreds of digits are described."""
    if isinstance(value, str | bytes):
        text = repr(value[: limit + 1])
    elif isinstance(value, dict | list | tuple):
        text = f"<{type(value).__name__} of {len(value)} items>"
    elif isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        text = f"<integer of about {int(value.bit_length() * 0.30103)} digits>"
    else:
        try:
            text = repr(value)
        except (ValueError, RecursionError):  # e.g. a numpy array of a huge nested object
            text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def strict_int(
    text: Any, field: str, low: int, high: int, error: type[Raytun3rError], where: str
) -> int:
    """Parse ``text`` as a decimal integer in ``[low, high]``, in exactly the syntax ``str(int)``
    writes: no spaces, no ``+``, no ``_`` separators, no leading zeros."""
    if not isinstance(text, str) or _INTEGER.fullmatch(text) is None:
        raise error(f"{where}: {field} must be a decimal integer, got {quote(text)}")
    value = int(text)
    if not low <= value <= high:
        raise error(f"{where}: {field} must be in [{low}, {high}], got {value}")
    return value


def json_depth(text: str) -> int:
    """Deepest nesting of objects and arrays in JSON ``text`` (strings skipped); linear time."""
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


def _refuse_duplicates(error: Callable[[str], Exception]) -> Callable[[list], dict]:
    def build(pairs: list[tuple[str, Any]]) -> dict:
        result: dict[str, Any] = {}
        for key, value in pairs:
            if key in result:
                raise error(f"duplicate key {quote(key)}")
            result[key] = value
        return result

    return build


def strict_json(text: Any, field: str, error: type[Raytun3rError], where: str) -> Any:
    """Parse JSON strictly: duplicate keys, ``NaN``/``Infinity``, nesting deeper than
    :data:`MAX_JSON_DEPTH` and integers of more than 18 digits are refused."""
    if not isinstance(text, str):
        raise error(f"{where}: {field} must be a JSON string, got {quote(text)}")
    if json_depth(text) > MAX_JSON_DEPTH:
        raise error(f"{where}: {field} is nested deeper than {MAX_JSON_DEPTH} levels")

    class _Refused(Exception):
        pass

    def refuse(message: str) -> Exception:
        return _Refused(message)

    def parse_int(digits: str) -> int:
        if len(digits.lstrip("-")) > 18:
            raise _Refused(f"integer of {len(digits)} digits")
        return int(digits)

    def parse_float(digits: str) -> float:
        value = float(digits)
        if not math.isfinite(value):
            raise _Refused(f"number {quote(digits)} overflows")
        return value

    def parse_constant(name: str) -> Any:
        raise _Refused(f"{name} is not JSON")

    try:
        return json.loads(
            text,
            object_pairs_hook=_refuse_duplicates(refuse),
            parse_int=parse_int,
            parse_float=parse_float,
            parse_constant=parse_constant,
        )
    except _Refused as refused:
        raise error(f"{where}: {field}: {refused}") from None
    except (json.JSONDecodeError, RecursionError, ValueError) as failure:
        raise error(f"{where}: {field} is not valid JSON ({quote(str(failure))})") from None


def read_safetensors(
    path: Path, max_bytes: int, error: type[Raytun3rError]
) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """Read a safetensors file strictly: ``(metadata, tensors)``.

    Refused with ``error``: a file over ``max_bytes``, a header that is not one JSON object of
    unique keys, metadata that is not a string-to-string map, tensor entries without exactly
    ``dtype``/``shape``/``data_offsets``, offsets that overlap, leave gaps or leave the file,
    shapes that disagree with their byte counts, and unknown dtypes.
    """
    where = str(path)

    def bad(detail: str) -> Raytun3rError:
        return error(f"{where}: not a readable safetensors file ({detail})")

    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise error(
                f"{where}: {size} bytes, more than the {max_bytes} an adapter file may have"
            )
        data = path.read_bytes()
    except OSError as failure:
        raise error(f"{where}: cannot be read ({failure.strerror or failure})") from None
    if len(data) < 8:
        raise bad(f"{len(data)} bytes, no header")
    (header_size,) = struct.unpack("<Q", data[:8])
    if header_size > len(data) - 8:
        raise bad(f"header of {header_size} bytes is cut off")
    try:
        header_text = data[8 : 8 + header_size].decode("utf-8")
    except UnicodeDecodeError:
        raise bad("header is not UTF-8") from None
    header = strict_json(header_text, "the safetensors header", error, where)
    if not isinstance(header, dict):
        raise bad("the header is not a JSON object")
    metadata = header.pop("__metadata__", {})
    if not isinstance(metadata, dict) or not all(
        isinstance(value, str) for value in metadata.values()
    ):
        raise bad("its metadata must map strings to strings")
    body = memoryview(data)[8 + header_size :]
    spans = []
    tensors: dict[str, torch.Tensor] = {}
    for name, entry in header.items():
        if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
            raise bad(f"tensor {quote(name)} has a malformed header entry")
        dtype_name, shape, offsets = entry["dtype"], entry["shape"], entry["data_offsets"]
        if dtype_name not in _DTYPES:
            raise bad(f"tensor {quote(name)} has unsupported dtype {quote(dtype_name)}")
        if (
            not isinstance(shape, list)
            or len(shape) > 8
            or not all(type(n) is int and 0 <= n < 2**31 for n in shape)
        ):
            raise bad(f"tensor {quote(name)} has a malformed shape {quote(shape)}")
        if (
            not isinstance(offsets, list)
            or len(offsets) != 2
            or not all(type(n) is int for n in offsets)
            or not 0 <= offsets[0] <= offsets[1] <= len(body)
        ):
            raise bad(f"tensor {quote(name)} has data offsets outside the file")
        dtype, item_size = _DTYPES[dtype_name]
        count = math.prod(shape)
        if (offsets[1] - offsets[0]) != count * item_size:
            raise bad(
                f"tensor {quote(name)} holds {offsets[1] - offsets[0]} bytes, its shape "
                f"{shape} needs {count * item_size}"
            )
        spans.append((offsets[0], offsets[1], name))
        raw = bytes(body[offsets[0] : offsets[1]])
        flat = (
            torch.frombuffer(bytearray(raw), dtype=dtype) if count else torch.empty(0, dtype=dtype)
        )
        tensors[name] = flat.reshape(shape)
    position = 0
    for begin, end, name in sorted(spans):
        if begin != position:
            raise bad(f"tensor {quote(name)} overlaps another or leaves a gap")
        position = end
    if position != len(body):
        raise bad(f"{len(body) - position} bytes after the last tensor")
    return metadata, tensors
