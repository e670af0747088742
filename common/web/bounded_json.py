"""JSON from a peer with its nesting bounded: a clear ``ValueError``, never a ``RecursionError``.

``json.loads`` recurses once per level of nesting, so ``[[[[...`` a few
thousand levels deep (a 64 KB WebSocket message holds 65 000) raises
``RecursionError``, which no handler written for bad input catches: the
connection's handler dies with a traceback and the peer's socket with it.
``loads`` refuses such text first, as the ``ValueError`` (``TooDeep``) any
other malformed JSON raises, so the caller's error reply covers it and the
socket stays open. Nothing the project exchanges nests more than a few levels.
"""

from __future__ import annotations

import json
import re
from typing import Any

#: levels of nesting any message may have (the project's own use a handful)
MAX_DEPTH = 32

#: what matters to the depth: brackets, and the quotes and escapes that hide them in strings
_TOKENS = re.compile(r'[\[\]{}"\\]')


class TooDeep(ValueError):
    """JSON nested deeper than the bound (a ``ValueError``, as any malformed JSON)."""


def nested_deeper_than(text: str, max_depth: int) -> bool:
    """Whether ``text`` opens more than ``max_depth`` brackets at once (outside strings).

    One pass over the brackets, quotes and backslashes only, stopping at the
    first level too many: cheap for the attack, linear for a large shallow text.
    """
    depth = 0
    in_string = False
    escaped_at = -1  # the position a backslash in a string escapes
    for m in _TOKENS.finditer(text):
        c, at = m.group(), m.start()
        if in_string:
            if at == escaped_at:
                continue
            if c == "\\":
                escaped_at = at + 1
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            if depth > max_depth:
                return True
        elif c in "]}":
            depth -= 1
    return False


def loads(raw: str | bytes | bytearray, max_depth: int = MAX_DEPTH) -> Any:
    """``json.loads`` of a peer's text; ``TooDeep`` (a ValueError) beyond ``max_depth`` levels.

    Bytes that are not UTF-8 raise ``UnicodeDecodeError``, a ``ValueError`` too.
    """
    text = bytes(raw).decode("utf-8") if isinstance(raw, bytes | bytearray) else raw
    if text.count("[") + text.count("{") > max_depth and nested_deeper_than(text, max_depth):
        raise TooDeep(f"JSON nested more than {max_depth} levels deep")
    try:
        return json.loads(text)
    except RecursionError:  # a bound above the interpreter's own: still a clear refusal
        raise TooDeep(f"JSON nested too deep to parse (bound {max_depth})") from None
