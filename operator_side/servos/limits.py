"""The bus-side check of goal counts, shared by every ServoBus.

The calibration already clips what the operator node computes; this is the
second line of defence, in the driver, so that no code path (a bug, a
message, a test) can put a count outside the calibrated limits on the wire.
Out-of-limit goals are refused as a whole, never clipped silently: a caller
that produced them has a bug worth seeing.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping

from common.errors import DeepXPalmError
from operator_side.servos.calibration import LinkGlideCalibration


class GoalOutOfLimitsError(DeepXPalmError, ValueError):
    """A goal count is outside its servo's calibrated limits; nothing was written."""


def check_goals(calibration: LinkGlideCalibration, goals: Mapping[int, int]) -> dict[int, int]:
    """Validate ``goals`` (servo id -> counts) and return them as plain ints.

    Raises ``GoalOutOfLimitsError`` naming every offending servo, so a refused
    write says at once which linkage and which limit.
    """
    # the 60 Hz case first: plain ints of known servos, all in range
    limits = calibration.limits_by_id
    if goals:
        for sid, value in goals.items():
            lim = limits.get(sid)
            if lim is None or type(sid) is not int or type(value) is not int:
                break
            if not lim[0] <= value <= lim[1]:
                break
        else:
            return dict(goals)
    by_id = {s.id: s for s in calibration.servos}
    if not goals:
        raise GoalOutOfLimitsError("write_goals got no goals; nothing to write")
    checked: dict[int, int] = {}
    problems: list[str] = []
    for sid, value in goals.items():
        servo = by_id.get(int(sid))
        if servo is None:
            problems.append(f"servo id {sid} is not calibrated (known ids {sorted(by_id)})")
            continue
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            if isinstance(value, numbers.Real) and float(value).is_integer():
                value = int(value)
            else:
                problems.append(f"servo {sid}: goal {value!r} is not an integer count")
                continue
        count = int(value)
        if not servo.min_counts <= count <= servo.max_counts:
            problems.append(
                f"servo {sid}: goal {count} outside limits [{servo.min_counts}, {servo.max_counts}]"
            )
            continue
        checked[int(sid)] = count
    if problems:
        raise GoalOutOfLimitsError(
            "refused to write servo goals (nothing sent): " + "; ".join(problems)
        )
    return checked
