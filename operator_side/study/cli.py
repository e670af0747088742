"""``deepxpalm study``: run the paper's perception study on a LinkGlide, and analyse it.

    deepxpalm study run --participant P01 --mode masked      # answer page on :8766
    deepxpalm study run --participant P01 --ui keyboard       # answers typed here
    deepxpalm study analyse results/ --out report/

Runs need no robot: each trial's stimulus is made here, as the robot would
render it, and sent to the servos through the node's own renderer.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from common.config.typed import defaults_toml
from common.errors import ConfigError
from common.process.command_line import add_overrides_argument, load_node_config, print_config
from operator_side.study.protocol import MODES, StudyConfig

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="study_command", metavar="{run,analyse}")
    run_p = sub.add_parser(
        "run",
        help="run (or resume) one participant's session",
        description="Training, practice and the 60-trial test for one participant and mode.",
    )
    _config_arguments(run_p)
    run_p.add_argument("--participant", help="participant code (names the results file)")
    run_p.add_argument("--mode", choices=MODES, help="rendering mode, overriding the config's")
    run_p.add_argument("--seed", type=int, help="trial order and grasps (default: from the id)")
    run_p.add_argument(
        "--ui",
        choices=("web", "keyboard", "simulated"),
        default="web",
        help="web: the answer page; keyboard: type the number here; "
        "simulated: a model participant (to try the study and its analysis)",
    )
    run_p.add_argument("--out", type=Path, default=Path("study-results"), help="results directory")
    run_p.add_argument("--host", default="127.0.0.1", help="answer page address (web ui)")
    run_p.add_argument("--port", type=int, default=8766, help="answer page port (web ui)")
    run_p.add_argument(
        "--no-training", action="store_true", help="skip training and practice (a re-run)"
    )
    an = sub.add_parser(
        "analyse",
        aliases=["analyze"],
        help="confusion matrices, recognition, response times, ANOVA; report with figures",
        description="Analyse every participant's results: a Markdown and JSON report with "
        "confusion-matrix heatmaps (PNG).",
    )
    an.add_argument("paths", nargs="*", type=Path, help="results files or directories")
    an.add_argument("--out", type=Path, default=Path("study-report"), help="report directory")
    an.add_argument("--mode", choices=MODES, help="only this mode (default: every mode found)")
    an.add_argument(
        "--confusion",
        type=Path,
        help="analyse a published confusion matrix (CSV) instead of results files",
    )
    an.add_argument(
        "--presentations",
        type=int,
        help="presentations per row when --confusion holds proportions (the paper: 50)",
    )
    an.add_argument("--alpha", type=float, default=0.05, help="significance level")
    an.add_argument("--title", default="", help="the report's heading")


def _config_arguments(parser: argparse.ArgumentParser) -> None:
    """A config file and overrides as the nodes take them, without the nodes' run options."""
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "Configuration: a TOML file with these keys, at the top level or under " + (
        "[study]. Defaults:\n\n"
        + "\n".join("  " + line for line in defaults_toml(StudyConfig, "study").splitlines())
    )
    parser.add_argument("--config", type=Path, help="TOML config (its [study] table)")
    add_overrides_argument(parser, "repetitions=5")
    parser.add_argument(
        "--print-config", action="store_true", help="print the effective config and exit"
    )


def run(args: argparse.Namespace) -> int:
    if args.study_command == "run":
        return _run(args)
    if args.study_command in ("analyse", "analyze"):
        return _analyse(args)
    print("deepxpalm study: choose 'run' or 'analyse' (see --help)", file=sys.stderr)
    return 2


def _raise_on_sigterm() -> None:
    """A stopped service lifts the palm like Ctrl-C does (through the same finally)."""

    def handler(signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)


def _run(args: argparse.Namespace) -> int:
    from common.devices.lifecycle import build_device
    from operator_side.servos import KINDS
    from operator_side.study.display import PalmDisplay
    from operator_side.study.protocol import (
        ResultsFile,
        check_participant,
        results_path,
        session_seed,
    )
    from operator_side.study.responders import (
        KeyboardResponder,
        Responder,
        SimulatedParticipant,
        WebResponder,
    )
    from operator_side.study.runner import Session

    config = load_node_config(args, StudyConfig, "study")
    if args.mode:
        config.mode = args.mode
    if args.seed is not None:
        config.seed = args.seed
    if args.print_config:
        print_config(config, "study")
        return 0
    if not args.participant:
        raise ConfigError("--participant is required (a code such as P01, never a name)")
    participant = check_participant(args.participant)
    seed = session_seed(config, participant)
    path = results_path(args.out, participant, config.mode)
    results = ResultsFile(path, participant, config.mode, seed)
    servos = build_device(KINDS, config.servos, "study.servos")
    display = PalmDisplay(servos, config.renderer, frame_rate_hz=config.frame_rate_hz)
    responder: Responder
    if args.ui == "web":
        responder = WebResponder(args.host, args.port)
    elif args.ui == "keyboard":
        responder = KeyboardResponder()
    else:
        responder = SimulatedParticipant(lambda: display.current_stimulus, seed=seed)
    _raise_on_sigterm()
    try:
        display.connect()
        responder.open()
        if isinstance(responder, WebResponder):
            print(f"answer page: {responder.url}  (results: {path})", flush=True)
        summary = Session(config, participant, seed, display, responder, results).run(
            training=not args.no_training
        )
    except KeyboardInterrupt:
        done = len(results.completed_test_trials())
        print(f"\nstopped; {done} test trials are saved in {path} (run again to resume)")
        return 130
    finally:
        try:
            display.close()
        finally:
            responder.close()
            results.close()
    print(
        f"{participant} {summary.mode}: {summary.correct} of {summary.test_trials} recognised "
        f"({100 * summary.recognition_rate:.1f}%); results in {path}"
    )
    return 0


def _analyse(args: argparse.Namespace) -> int:
    from operator_side.study.analysis import (
        analyse_confusion,
        analyse_trials,
        load_test_trials,
        read_confusion_csv,
    )
    from operator_side.study.report import p_text, write_report

    if args.confusion:
        counts = read_confusion_csv(args.confusion, args.presentations)
        analyses = [analyse_confusion(counts, args.mode or args.confusion.stem)]
    else:
        if not args.paths:
            raise ConfigError("give results files or directories (or --confusion FILE.csv)")
        trials = load_test_trials(args.paths)
        modes = [args.mode] if args.mode else sorted({str(t.get("mode")) for t in trials})
        if not modes:
            raise ConfigError("no test trials found")
        analyses = [analyse_trials(trials, m, args.alpha) for m in modes]
    paths = write_report(analyses, args.out, args.title)
    for a in analyses:
        who = f"{len(a.participants)} participants, " if a.participants else ""
        line = (
            f"{a.mode}: {who}{a.trials} trials; recognised {100 * a.overall:.2f}%, "
            f"angle only {100 * a.angle_only:.2f}%"
        )
        if a.response_times_s.size:
            line += f", mean response time {a.response_times_s.mean():.2f} s"
        if a.anova_pattern is not None and a.anova_pattern.f is not None:
            an = a.anova_pattern
            line += f"; RM-ANOVA F({an.ddof1:g}, {an.ddof2:g}) = {an.f:.3f}, p {p_text(an.p)}"
        print(line)
    print(f"report: {paths['markdown']}")
    return 0
