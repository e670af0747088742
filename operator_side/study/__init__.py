"""The perception study of the paper (section VI), on this project's LinkGlide.

``deepxpalm study run`` trains a participant on the 12 patterns and records
60 answers; ``deepxpalm study analyse`` turns every participant's answers
into the paper's numbers (docs/study.md).
"""
