"""`deepxpalm calibrate`: measure LinkGlide's servo calibration and store it.

The steps a lab runs once per device (docs/servos.md walks through them):

    deepxpalm calibrate --file cal.toml --write-defaults
    deepxpalm calibrate --file cal.toml --port /dev/serial/by-id/... --capture-limits 20
    deepxpalm calibrate --file cal.toml --port /dev/serial/by-id/... --capture-zero
    deepxpalm calibrate --file cal.toml --set 4 direction=-1
    deepxpalm calibrate --file cal.toml --port /dev/serial/by-id/... --show

Capturing turns torque off so the linkages can be moved by hand. Nothing is
written to the file until every value passes the calibration's own checks.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from common.errors import ConfigError
from operator_side.servos.calibration import (
    COUNTS_PER_RAD,
    LinkGlideCalibration,
    ServoCalibration,
    load_calibration,
    save_calibration,
)
from operator_side.servos.feetech import FeetechConfig, FeetechServoBus

log = logging.getLogger(__name__)

_SETTABLE = ("zero_counts", "direction", "min_counts", "max_counts")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--file",
        default="linkglide-calibration.toml",
        help="the calibration TOML to read and update",
    )
    parser.add_argument("--port", help="servo bus adapter (use its /dev/serial/by-id/... name)")
    parser.add_argument("--baudrate", type=int, default=1_000_000, help="servo bus rate")
    parser.add_argument(
        "--simulate", action="store_true", help="use a fake STS bus instead of --port (to practise)"
    )
    parser.add_argument(
        "--write-defaults", action="store_true", help="start the file from the project defaults"
    )
    parser.add_argument("--force", action="store_true", help="let --write-defaults overwrite")
    parser.add_argument(
        "--capture-limits",
        type=float,
        metavar="SECONDS",
        help="torque off; move every linkage through its whole safe range within SECONDS; "
        "min/max seen (minus --margin) become the limits",
    )
    parser.add_argument(
        "--margin", type=int, default=30, help="counts kept inside the captured range (default 30)"
    )
    parser.add_argument(
        "--capture-zero",
        action="store_true",
        help="torque off; hold every linkage in the reference pose; its counts become the zero",
    )
    parser.add_argument(
        "--reference-deg",
        type=float,
        nargs=2,
        default=(90.0, 90.0),
        metavar=("TAU_A", "TAU_E"),
        help="servo angles of the reference pose, degrees counter-clockwise from +X "
        "(default 90 90: both proximal links upright, pointing at the palm)",
    )
    parser.add_argument(
        "--set",
        nargs=2,
        action="append",
        default=[],
        metavar=("ID", "KEY=VALUE"),
        help=f"edit one value, e.g. --set 4 direction=-1 (keys: {', '.join(_SETTABLE)})",
    )
    parser.add_argument(
        "--torque-off", action="store_true", help="only turn torque off (to free the linkages)"
    )
    parser.add_argument("--show", action="store_true", help="print the calibration (and pose)")
    parser.add_argument("--yes", action="store_true", help="do not wait for Enter (scripts)")


def run(args: argparse.Namespace) -> int:
    path = Path(args.file)
    if args.write_defaults:
        if path.exists() and not args.force:
            raise ConfigError(f"{path} exists; add --force to replace it with the defaults")
        save_calibration(LinkGlideCalibration(), path)
        print(f"wrote the default calibration to {path}")
    if path.exists():
        cal = load_calibration(path)
    else:
        print(f"{path} does not exist yet: starting from the defaults")
        cal = LinkGlideCalibration()
    original = dataclasses.asdict(cal)
    servos = {s.id: dataclasses.replace(s) for s in cal.servos}

    for sid_text, assignment in args.set:
        _apply_set(servos, sid_text, assignment)

    needs_bus = args.capture_limits or args.capture_zero or args.torque_off
    needs_bus = needs_bus or (args.show and (args.port or args.simulate))
    if needs_bus:
        with _open_bus(args, _rebuild(servos)) as bus:
            if args.torque_off or args.capture_limits or args.capture_zero:
                bus.set_torque(False)
                print("torque is off: the linkages move freely")
            if args.capture_limits:
                _capture_limits(bus, servos, args.capture_limits, args.margin, args.yes)
            if args.capture_zero:
                _capture_zero(bus, servos, args.reference_deg, args.yes)
            if args.show:
                _show(_rebuild(servos), bus.read_positions())
    elif args.show:
        _show(_rebuild(servos), None)

    new = _rebuild(servos)  # runs every check before anything is written
    measured = bool(args.set or args.capture_limits or args.capture_zero)
    if dataclasses.asdict(new) != original or (measured and not path.exists()):
        save_calibration(new, path)
        print(f"saved {path}")
    return 0


def _rebuild(servos: dict[int, ServoCalibration]) -> LinkGlideCalibration:
    return LinkGlideCalibration(servos=[dataclasses.replace(servos[i]) for i in sorted(servos)])


def _apply_set(servos: dict[int, ServoCalibration], sid_text: str, assignment: str) -> None:
    try:
        sid = int(sid_text)
        key, value_text = assignment.split("=", 1)
        value = int(value_text)
    except ValueError:
        raise ConfigError(f"--set {sid_text} {assignment}: expected ID KEY=INTEGER") from None
    if sid not in servos:
        raise ConfigError(f"--set: servo id {sid} is not one of {sorted(servos)}")
    if key not in _SETTABLE:
        raise ConfigError(f"--set: {key!r} is not one of {', '.join(_SETTABLE)}")
    servos[sid] = dataclasses.replace(servos[sid], **{key: value})  # re-checked on build


@contextlib.contextmanager
def _open_bus(args: argparse.Namespace, cal: LinkGlideCalibration) -> Iterator[FeetechServoBus]:
    with contextlib.ExitStack() as stack:
        port = args.port
        window: dict[str, float | int | None] = {}
        if args.simulate:
            from operator_side.servos.sts_sim import FakeStsBus, SimulatedFeetechConfig

            port = stack.enter_context(FakeStsBus()).port
            print(f"simulated STS bus on {port}")
            # the simulated kind's reply window and retries: the fake servos answer from a
            # thread of this process, which a busy machine holds up past a real bus's 34 ms
            driver = SimulatedFeetechConfig().driver
            window = {"retries": driver.retries, "reply_timeout_ms": driver.reply_timeout_ms}
        if not port:
            raise ConfigError("this step talks to the servos: give --port (or --simulate)")
        config = FeetechConfig(
            port=port, baudrate=args.baudrate, calibration=cal, torque_on_connect=False, **window
        )
        yield stack.enter_context(FeetechServoBus(config))


def _prompt(text: str, yes: bool) -> None:
    if yes:
        print(text)
        return
    input(text + " Press Enter when ready. ")


def _capture_limits(
    bus: FeetechServoBus,
    servos: dict[int, ServoCalibration],
    seconds: float,
    margin: int,
    yes: bool,
) -> None:
    _prompt(
        f"Move every linkage slowly through its whole safe range, within {seconds:g} s "
        "after you start (never force a joint against the palm or its stop).",
        yes,
    )
    lo: dict[int, int] = {}
    hi: dict[int, int] = {}
    end = time.monotonic() + seconds
    samples = 0
    while True:
        for sid, counts in bus.read_positions().items():
            lo[sid] = min(lo.get(sid, counts), counts)
            hi[sid] = max(hi.get(sid, counts), counts)
        samples += 1
        if time.monotonic() >= end:
            break
        time.sleep(0.02)
    for sid in sorted(lo):
        new_min, new_max = lo[sid] + margin, hi[sid] - margin
        if new_max - new_min < 100:
            raise ConfigError(
                f"servo {sid} moved only over [{lo[sid]}, {hi[sid]}] counts in {seconds:g} s: "
                "move every linkage through its range (or lower --margin)"
            )
        servos[sid] = dataclasses.replace(servos[sid], min_counts=new_min, max_counts=new_max)
        print(f"servo {sid}: seen [{lo[sid]}, {hi[sid]}] -> limits [{new_min}, {new_max}]")
    log.info("captured limits from %d reads", samples)


def _capture_zero(
    bus: FeetechServoBus,
    servos: dict[int, ServoCalibration],
    reference_deg: tuple[float, float],
    yes: bool,
) -> None:
    _prompt(
        f"Hold every linkage in the reference pose (tau_a = {reference_deg[0]:g} deg, "
        f"tau_e = {reference_deg[1]:g} deg).",
        yes,
    )
    reads = [bus.read_positions() for _ in range(5)]
    for sid in sorted(servos):
        values = sorted(r[sid] for r in reads)
        counts = values[len(values) // 2]
        if values[-1] - values[0] > 10:
            raise ConfigError(
                f"servo {sid} moved by {values[-1] - values[0]} counts while capturing: hold still"
            )
        side = (sid - 1) % 2  # odd ids are the A side, even ids the E side
        ref_rad = math.radians(reference_deg[side])
        s = servos[sid]
        zero = round(counts - s.direction * ref_rad * COUNTS_PER_RAD)
        if not 0 <= zero <= 4095:
            raise ConfigError(
                f"servo {sid}: zero would be {zero} counts (present {counts}); "
                "is its direction right? (--set ID direction=-1)"
            )
        if not s.min_counts <= counts <= s.max_counts:
            print(
                f"warning: servo {sid} is at {counts}, outside its limits "
                f"[{s.min_counts}, {s.max_counts}]: capture the limits again",
                file=sys.stderr,
            )
        servos[sid] = dataclasses.replace(s, zero_counts=zero)
        print(f"servo {sid}: present {counts} at {math.degrees(ref_rad):g} deg -> zero {zero}")


def _show(cal: LinkGlideCalibration, present: dict[int, int] | None) -> None:
    header = f"{'id':>3} {'zero':>6} {'dir':>4} {'min':>6} {'max':>6}"
    if present is not None:
        header += f" {'present':>8} {'angle deg':>10}"
    print(header)
    for s in sorted(cal.servos, key=lambda s: s.id):
        line = f"{s.id:>3} {s.zero_counts:>6} {s.direction:>4} {s.min_counts:>6} {s.max_counts:>6}"
        if present is not None:
            p = present[s.id]
            angle = math.degrees((p - s.zero_counts) / (s.direction * COUNTS_PER_RAD))
            line += f" {p:>8} {angle:>10.1f}"
        print(line)
