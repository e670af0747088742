"""Clocks: the monotonic clock and pacing (clock.py), the peer's offset (clock_sync.py)."""
