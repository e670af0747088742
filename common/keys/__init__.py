"""Who may connect: the CURVE keys of each hop (curve.py) and the roster (roster.py)."""
