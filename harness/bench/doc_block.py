"""A marked block of a doc, rewritten by the section that measures it.

Pages other than the bench's report carry a section's table between two
HTML comments (``<!-- name:begin -->`` ... ``<!-- name:end -->``); a run
writes its table between them and leaves the rest of the page as it was.
"""

from __future__ import annotations

from pathlib import Path


def replace_block(path: Path, begin: str, end: str, lines: list[str]) -> None:
    """Put ``lines`` between the markers ``begin`` and ``end`` in ``path`` (markers kept).

    A page without both markers, in that order, is left alone and named in a
    ValueError: a table written elsewhere would silently go stale.
    """
    text = path.read_text()
    start = text.find(begin)
    stop = text.find(end, start + len(begin)) if start >= 0 else -1
    if stop < 0:
        raise ValueError(f"{path} has no {begin} ... {end} block to write the table into")
    path.write_text(text[:start] + "\n".join([begin, *lines, end]) + text[stop + len(end) :])
