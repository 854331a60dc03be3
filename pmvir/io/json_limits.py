"""JSON from untrusted sources, with its nesting depth and number sizes bounded.

Python's :func:`json.loads` turns a 5000-digit integer into a ``ValueError``
(the int/str conversion limit) and a document nested 50,000 deep into a
``RecursionError``; both escape a ``JSONDecodeError`` handler. :func:`loads`
refuses them, and every other malformed document, with one
:class:`JsonError` that says where and what.

>>> loads('{"a": [1, 2.5, "x"]}', source="options")
{'a': [1, 2.5, 'x']}
>>> loads("[" * 100 + "]" * 100, source="options")
Traceback (most recent call last):
...
pmvir.io.json_limits.JsonError: options: JSON nested deeper than 64 levels
"""

from __future__ import annotations

import json
from typing import Any

from pmvir.errors import PmvirError

#: Deepest nesting of arrays and objects accepted.
MAX_DEPTH = 64
#: Most characters in one number literal (digits, sign, point, exponent).
MAX_NUMBER_CHARS = 64


class JsonError(PmvirError, ValueError):
    """A JSON document is malformed, nested too deeply, or has an oversized number.

    Args:
        source: what the document is (a file name or a request field), for the message.
        problem: what was expected and what came.
    """

    def __init__(self, source: str, problem: str):
        self.source = source
        self.problem = problem
        super().__init__(f"{source}: {problem}")


def _number(kind: type) -> Any:
    def parse(text: str) -> Any:
        if len(text) > MAX_NUMBER_CHARS:
            raise _NumberTooLong(text)
        return kind(text)

    return parse


class _NumberTooLong(Exception):
    pass


def _depth(doc: Any) -> int:
    """Nesting depth of a parsed document (iterative: no recursion on hostile input)."""
    deepest, stack = 0, [(doc, 0)]
    while stack:
        node, d = stack.pop()
        if isinstance(node, dict):
            node = list(node.values())
        if isinstance(node, list):
            deepest = max(deepest, d + 1)
            stack.extend((x, d + 1) for x in node if isinstance(x, (dict, list)))
    return deepest


def loads(data: str | bytes, *, source: str, max_depth: int = MAX_DEPTH) -> Any:
    """Parse a JSON document from an untrusted source.

    Args:
        data: the document (bytes are decoded as UTF-8).
        source: what the document is, for error messages (e.g. ``capture.json``).
        max_depth: deepest nesting of arrays/objects accepted.

    Returns:
        The parsed document (dicts, lists, str, int, float, bool, None).

    Raises:
        JsonError: not UTF-8, not JSON, a number literal of more than :data:`MAX_NUMBER_CHARS`
            characters, or nesting deeper than ``max_depth``. (NaN, Infinity and 1e999 parse as
            floats: the models they are validated by name the field that must be finite.)
    """
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
    except UnicodeDecodeError as exc:
        raise JsonError(source, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        doc = json.loads(
            text,
            parse_int=_number(int),
            parse_float=_number(float),
        )
    except _NumberTooLong as exc:
        raise JsonError(
            source, f"a number of {len(str(exc))} characters; at most {MAX_NUMBER_CHARS} are accepted"
        ) from None
    except RecursionError:
        raise JsonError(source, f"JSON nested deeper than {max_depth} levels") from None
    except json.JSONDecodeError as exc:
        raise JsonError(source, f"not valid JSON: {exc}") from None
    if _depth(doc) > max_depth:
        raise JsonError(source, f"JSON nested deeper than {max_depth} levels")
    return doc
