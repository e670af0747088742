"""Typed configuration: dataclasses with their defaults, filled from TOML.

typed.py: the dataclass fields, their reasons, loading and printing;
overrides.py: ``--set a.b=value`` on top of a file.
"""
