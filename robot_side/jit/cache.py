"""``numba.njit`` as the robot side uses it: cached on disk where it can be.

The compiled kernels (the classifier's forward pass, the frame step, the
tactile conversion) take about 2 s to compile and a fraction of a second to
load from numba's cache. numba caches beside the source or in the user's
cache directory (``NUMBA_CACHE_DIR`` overrides both) and refuses to define a
cached function when none is writable, as under a read-only install with no
home. Then the kernels compile in memory at every start instead of failing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numba

log = logging.getLogger(__name__)

_warned = False

#: every function compiled through ``njit``, for ``cache_counts``
COMPILED: list[Any] = []


def njit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(cache=True, nogil=True, **options)``, or without the cache if it cannot be."""

    def wrap(fn: Callable[..., Any]) -> Any:
        global _warned
        try:
            compiled = numba.njit(cache=True, nogil=True, **options)(fn)
        except RuntimeError as e:  # "cannot cache function ...: no locator available"
            if not _warned:
                _warned = True
                log.warning(
                    "numba cannot cache compiled code (%s); compiling at every start instead. "
                    "Set NUMBA_CACHE_DIR to a writable directory to cache it",
                    e,
                )
            compiled = numba.njit(cache=False, nogil=True, **options)(fn)
        COMPILED.append(compiled)
        return compiled

    return wrap


def cache_counts() -> tuple[int, int]:
    """(signatures loaded from the cache, signatures compiled) in this process so far."""
    hits = sum(sum(f.stats.cache_hits.values()) for f in COMPILED)
    misses = sum(sum(f.stats.cache_misses.values()) for f in COMPILED)
    return hits, misses
