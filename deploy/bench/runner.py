"""Running the sections: one core, one classifier, every section isolated from the others.

Kept apart from the command-line module, which sets the thread variables at
import (they must precede numpy), so that tests can call ``run_bench``
without changing their own process's environment.
"""

from __future__ import annotations

import logging
import os
import platform
import subprocess
import time
import traceback
from dataclasses import asdict
from pathlib import Path
from typing import Any

from deploy.bench.sizes import Sizes

log = logging.getLogger(__name__)


def _git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _versions() -> dict[str, str | None]:
    import importlib.metadata as md

    out: dict[str, str | None] = {"python": platform.python_version()}
    for pkg in (
        "numpy",
        "pyzmq",
        "msgpack",
        "numba",
        "onnxruntime",
        "torch",
        "scipy",
        "feetech-servo-sdk",
    ):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_bench(
    sizes: Sizes,
    preset: str,
    skip: set[str],
    cpu: int | None,
    models: list[Path],
    progress: bool = False,
) -> dict[str, Any]:
    """Every section not skipped; a section that fails is reported, not fatal."""
    from deploy.bench import timing

    load_before = timing.machine_load()
    commit = _git_commit()  # before: others may commit while the bench runs
    with timing.one_core(cpu) as core:
        results = _measure(sizes, preset, skip, core, models, progress)
    results["git_commit"] = commit
    results["machine"]["load_before"] = load_before
    results["machine"]["load_after"] = timing.machine_load()
    return results


def _measure(
    sizes: Sizes,
    preset: str,
    skip: set[str],
    core: int,
    models: list[Path],
    progress: bool,
) -> dict[str, Any]:
    from deploy.bench import timing
    from robot_side.perception import DEFAULT_BACKEND_ORDER, load_classifier
    from robot_side.perception.inference import backend_installed

    classifier = load_classifier()  # the node's default: shipped model, first installed backend
    timing.limit_torch_threads()
    default_backend = next(b for b in DEFAULT_BACKEND_ORDER if backend_installed(b))
    t_start = time.monotonic()
    sections: dict[str, Any] = {}

    def section(name: str, fn: Any) -> Any:
        if name in skip:
            sections[name] = {"skipped": True}
            return None
        t = time.monotonic()
        if progress:
            print(f"[bench] {name} ...", flush=True)
        try:
            out = fn()
        except Exception as e:  # one broken section must not lose the others
            log.exception("section %s failed", name)
            sections[name] = {"error": f"{type(e).__name__}: {e}", "trace": traceback.format_exc()}
            return None
        out["seconds"] = round(time.monotonic() - t, 2)
        sections[name] = out
        if progress:
            print(f"[bench] {name}: {out['seconds']} s", flush=True)
        return out

    from deploy.bench import stages

    def budget_fn() -> dict[str, Any]:
        out = stages.stage_budget(sizes.stage_frames, classifier)
        out["paced"] = stages.stage_budget(
            sizes.stage_paced_frames, classifier, pace_hz=sizes.pace_hz
        )
        return out

    def inproc_fn() -> dict[str, Any]:
        out = stages.end_to_end_inproc(sizes.e2e_frames, classifier)
        out["paced"] = stages.end_to_end_inproc(
            sizes.e2e_paced_frames, classifier, pace_hz=sizes.pace_hz
        )
        return out

    budget = section("stages", budget_fn)
    # the costs a frame pays in the field (paced), for the savings and the scale model
    medians = {k: v["median_us"] for k, v in budget["paced"]["stages"].items()} if budget else {}
    section("e2e_inproc", inproc_fn)

    def tcp() -> dict[str, Any]:
        from deploy.bench.e2e_tcp import end_to_end_tcp, loopback_floor

        out = end_to_end_tcp(sizes.tcp_frames, sizes.tcp_rate_hz, classifier, core)
        out["floor"] = loopback_floor(sizes.tcp_frames, sizes.tcp_rate_hz, core)
        others = sorted(timing.original_affinity() - {core})
        if others:  # two machines in the field: the operator on a core of its own
            out["operator_on_other_core"] = end_to_end_tcp(
                sizes.tcp_frames, sizes.tcp_rate_hz, classifier, core, peer_cpu=others[0]
            )
            out["operator_on_other_core"]["floor"] = loopback_floor(
                sizes.tcp_frames, sizes.tcp_rate_hz, core, peer_cpu=others[0]
            )
        return out

    section("e2e_tcp", tcp)

    def downsizing() -> dict[str, Any]:
        from deploy.bench.downsizing import downsizing_tradeoff
        from deploy.bench.fixtures import frame_set

        fs = frame_set(sizes.ds_repeats, seed=0)
        a, p = classifier.predict(fs.frames)
        return downsizing_tradeoff(fs, 3 * a + p, sizes.ds_calls)

    section("downsizing", downsizing)

    def clf() -> dict[str, Any]:
        from deploy.bench import classifier as cb
        from deploy.bench.fixtures import frame_set

        eval_default = frame_set(sizes.clf_eval_repeats, seed=11)
        eval_rand = (
            cb.randomized_eval_set(sizes.clf_randomized_repeats)
            if sizes.clf_randomized_repeats > 0
            else None
        )
        out = cb.classifier_tradeoff(
            cb.find_models(models),
            list(sizes.clf_backends_default),
            list(sizes.clf_backends_others),
            eval_default,
            eval_rand,
            sizes.clf_calls,
            sizes.clf_paced_calls,
            1.0 / sizes.pace_hz,
        )
        timing.limit_torch_threads()
        return out

    section("classifier", clf)

    def ik() -> dict[str, Any]:
        from deploy.bench.ik import ik_tradeoff

        return ik_tradeoff(
            sizes.ik_grid_mm,
            sizes.ik_shell_points,
            sizes.ik_numeric_points,
            sizes.ik_calls,
            least_squares=sizes.ik_least_squares,
        )

    section("ik", ik)

    def skipping() -> dict[str, Any]:
        from deploy.bench.skipping import skipping as run_skipping

        return run_skipping(classifier, medians, sizes.skip_cycles)

    section("skipping", skipping)

    def stress() -> dict[str, Any]:
        from deploy.bench.stress import stress as run_stress

        return run_stress(
            classifier,
            sizes.stress_grid_mm,
            sizes.stress_shell_points,
            sizes.stress_stimuli,
            sizes.stress_random_frames,
        )

    section("stress", stress)
    demo_frames: list[Any] = []

    def frames_for_nodes() -> list[Any]:
        if not demo_frames:
            from deploy.bench.skipping import demo_frames as make

            demo_frames.extend(make("demo", 1.0 if preset == "full" else 0.3)[0])
        return demo_frames

    def node_cpu() -> dict[str, Any]:
        from deploy.bench.nodecpu import run_nodes

        # the nodes are processes of their own: unpin them (they inherit this affinity)
        return run_nodes(frames_for_nodes(), 120.0, sizes.node_warmup_s, sizes.node_measure_s)

    def scale() -> dict[str, Any]:
        from deploy.bench import scale as sc
        from robot_side.config import RobotConfig

        cap = RobotConfig().publish_rate_hz
        transit = (budget or {}).get("transit", {}).get("tcp_loopback", {}).get("median_us", 0.0)
        # the sender's share of a one-process round trip: half, a rough split
        out: dict[str, Any] = {
            "cap_hz": cap,
            "modelled": sc.modelled(medians, transit / 2, sizes.scale_rates, cap),
        }
        if sizes.scale_measured:
            out["measured"] = sc.measured(
                frames_for_nodes(),
                sizes.scale_rates,
                sizes.node_warmup_s,
                sizes.node_measure_s / 2,
                cap,
                sizes.scale_backends,
            )
        return out

    section("node_cpu", node_cpu)

    def command_path() -> dict[str, Any]:
        from deploy.bench.command_path import measure

        return measure(sizes.cmd_flood_messages, 2.0, sizes.cmd_cost_messages)

    section("command_path", command_path)
    section("scale", scale)

    def video() -> dict[str, Any]:
        from deploy.bench.video import glass_to_glass

        return glass_to_glass(sizes.video_frames)

    section("video", video)

    def netsim() -> dict[str, Any]:
        from deploy.bench.netsim_fidelity import measure as netsim_fidelity

        return netsim_fidelity(sizes.netsim_seconds, sizes.netsim_scenarios)

    section("netsim", netsim)
    return {
        "generated_by": f"deepxpalm bench{'' if preset == 'full' else ' --size ' + preset}",
        "preset": preset,
        "sizes": asdict(sizes),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "git_commit": _git_commit(),
        "machine": {
            "cpu": _cpu_model(),
            "cores": os.cpu_count(),
            "pinned_core": core,
            "kernel": platform.release(),
        },
        "versions": _versions(),
        "defaults": _defaults(default_backend),
        "timer_overhead_ns": timing.timer_overhead_ns(),
        "wakeup_cpu_us": timing.wakeup_cpu_us(),
        "cold_call": timing.cold_call_us(),
        "full_collection": timing.full_collection_ms(),
        "total_seconds": round(time.monotonic() - t_start, 1),
        "sections": sections,
    }


def _defaults(backend: str) -> dict[str, Any]:
    from robot_side.config import RobotConfig
    from robot_side.perception.weights import DEFAULT_MODEL, read_weights

    cfg = RobotConfig()
    _, meta = read_weights(DEFAULT_MODEL)
    return {
        "method": cfg.render.method,
        "order": cfg.render.order,
        "mode": cfg.render.mode,
        "backend": cfg.classifier.backend or backend,
        "backend_configured": cfg.classifier.backend,
        "model_width": meta.get("model", {}).get("width"),
        "publish_rate_hz": cfg.publish_rate_hz,
        "deadband_n": cfg.render.deadband_n,
    }
