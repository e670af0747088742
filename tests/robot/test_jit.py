"""Compiled kernels still work where numba cannot cache them (a read-only install)."""

from __future__ import annotations

import logging

import pytest

numba = pytest.importorskip("numba")

from robot_side.jit import cache as jit  # noqa: E402


def test_a_kernel_without_a_writable_cache_compiles_in_memory(monkeypatch, caplog) -> None:
    real = numba.njit

    def refusing(*args, **options):
        if options.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'x'")
        return real(*args, **options)

    monkeypatch.setattr(jit.numba, "njit", refusing)
    monkeypatch.setattr(jit, "_warned", False)
    with caplog.at_level(logging.WARNING, logger="robot_side.jit.cache"):

        @jit.njit()
        def twice(x):
            return 2 * x

    assert twice(21) == 42
    assert "NUMBA_CACHE_DIR" in caplog.text
