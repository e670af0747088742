"""Running the sections: one core, one classifier, every section isolated from the others.

Kept apart from the command-line module, which sets the thread variables at
import (they must precede numpy), so that tests can call ``run_bench``
without changing their own process's environment.
"""

from __future__ import annotations

import logging
import os
import platform
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any

from harness.bench.section import Context, Section
from harness.bench.sizes import Sizes
from harness.bench.stamp import git_commit

if TYPE_CHECKING:
    from harness.bench.progress import BenchProgress

log = logging.getLogger(__name__)


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
    progress: BenchProgress | None = None,
    task_cells: Path | None = None,
) -> dict[str, Any]:
    """Every section not skipped; a section that fails is reported, not fatal.

    ``progress`` is told which sections run, when each starts and ends, and how far
    the running one is through its cells or trials (the CLI draws it).
    """
    from harness.bench import timing

    load_before = timing.machine_load()
    commit = git_commit()  # before: others may commit while the bench runs
    with timing.one_core(cpu) as core:
        results = _measure(sizes, preset, skip, core, models, progress, task_cells)
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
    progress: BenchProgress | None,
    task_cells: Path | None = None,
) -> dict[str, Any]:
    from harness.bench import timing
    from harness.bench.sections import SECTIONS
    from robot_side.perception import DEFAULT_BACKEND_ORDER
    from robot_side.perception.inference import backend_installed

    ctx = Context(preset=preset, core=core, models=models, task_cells=task_cells)
    if progress is not None:
        ctx.steps = progress.steps
        ctx.say = progress.note
        progress.begin([s.name for s in SECTIONS if s.name not in skip])
    timing.limit_torch_threads()
    default_backend = next(b for b in DEFAULT_BACKEND_ORDER if backend_installed(b))
    t_start = time.monotonic()
    smallest = preset == "smallest"
    sections: dict[str, Any] = {}
    for section in SECTIONS:
        if section.name in skip:
            # asked to skip it (--skip, --only), or a section --quick leaves out
            why = "quick" if preset == "quick" and not section.quick else "skip"
            sections[section.name] = {"skipped": True, "why": why}
            continue
        sections[section.name] = _run_section(section, ctx, sizes[section.name], progress)
    return {
        "generated_by": f"deepxpalm bench{'' if preset == 'full' else ' --size ' + preset}",
        "preset": preset,
        "sizes": sizes.flat(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "git_commit": git_commit(),
        "machine": {
            "cpu": _cpu_model(),
            "cores": os.cpu_count(),
            "pinned_core": core,
            "kernel": platform.release(),
        },
        "versions": _versions(),
        "defaults": _defaults(default_backend),
        "timer_overhead_ns": timing.timer_overhead_ns(),
        # the smallest preset's numbers mean nothing (sizes.py): a tenth of the samples
        "wakeup_cpu_us": timing.wakeup_cpu_us(seconds=0.2 if smallest else 2.0),
        "cold_call": timing.cold_call_us(n=15 if smallest else 150),
        "full_collection": timing.full_collection_ms(),
        "total_seconds": round(time.monotonic() - t_start, 1),
        "sections": sections,
    }


def _run_section(
    section: Section, ctx: Context, sizes: Any, progress: BenchProgress | None
) -> dict[str, Any]:
    """One section's results, or its error: one broken section must not lose the others.

    Its wall time is stored with it (``seconds``): the next run's ETA reads it.
    """
    t = time.monotonic()
    if progress:
        progress.start(section.name)
    try:
        out = section.measure(ctx, sizes)
    except Exception as e:
        log.exception("section %s failed", section.name)
        error = f"{type(e).__name__}: {e}"
        if progress:
            progress.end(section.name, round(time.monotonic() - t, 2), error)
        return {"error": error, "trace": traceback.format_exc()}
    out["seconds"] = round(time.monotonic() - t, 2)
    if progress:
        progress.end(section.name, out["seconds"])
    return out


def _defaults(backend: str) -> dict[str, Any]:
    from robot_side.node.config import RobotConfig
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
