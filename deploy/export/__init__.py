"""Recordings to LeRobot datasets (format v3): ``deepxpalm export``.

``session`` reads a recorded session in time order, ``resample`` turns it
into rows at a fixed rate and cuts the rows into episodes, ``lerobot_v3``
writes the rows as LeRobot's parquet layout, ``schema`` names every feature,
``curation`` applies the operator's episode marks, ``exclude`` and the task
file.
docs/datasets.md describes the result.
"""
