"""What every node's command line shares: a config file, overrides, defaults in --help."""

from __future__ import annotations

import argparse
import dataclasses
import gc
import importlib
import json
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TypeVar

from common.config.overrides import apply_overrides
from common.config.typed import check_secret_file, config_toml, defaults_toml, from_dict, load_toml
from common.process.sd_notify import watch_node
from common.process.signals import on_signal, stop_on_signals

T = TypeVar("T")


def add_overrides_argument(parser: argparse.ArgumentParser, example: str) -> None:
    """``--set KEY=VALUE`` (repeatable) into ``args.overrides``, as every config CLI takes it."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"override one setting, e.g. --set {example} (repeatable)",
    )


def add_config_arguments(
    parser: argparse.ArgumentParser,
    cls: type,
    section: str,
    *,
    example: str | None = None,
    record: bool = False,
) -> None:
    """``--config``, ``--set``, ``--print-config``, ``--stats-file``, ``--duration``; ``--record``
    only where the command records (``run_node``'s nodes): an option offered is one it uses.

    ``example``: the ``--set`` help's example, a key of ``cls`` (``KEY=VALUE`` without the
    section); unset: the first plain setting of ``cls`` at its default. Every such example
    runs with ``--print-config`` in tests/deploy/test_help_examples.py.
    """
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        f"Configuration: a TOML file with these keys, either at the top level or under "
        f"[{section}] (so a whole scene file works). Defaults:\n\n"
        + _indent(defaults_toml(cls, section))
    )
    parser.add_argument("--config", type=Path, help="TOML config or scene file")
    add_overrides_argument(parser, f"{section}.{example or example_setting(cls)}")
    parser.add_argument(
        "--print-config", action="store_true", help="print the effective config and exit"
    )
    parser.add_argument("--stats-file", type=Path, help="write final counters here as JSON on exit")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    if record:
        parser.add_argument(
            "--record", type=Path, metavar="FILE", help="record the session to this MCAP file"
        )


def example_setting(cls: type) -> str:
    """``key=value``: the first setting of ``cls`` that is a plain value, at its default."""
    defaults = cls()
    for field in dataclasses.fields(cls):
        value = getattr(defaults, field.name)
        if isinstance(value, bool):
            return f"{field.name}={str(value).lower()}"
        if isinstance(value, int | float) or (isinstance(value, str) and value.isidentifier()):
            return f"{field.name}={value}"
    raise ValueError(f"{cls.__name__} has no plain setting to show as an example")


def _indent(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())


def load_node_config(
    args: argparse.Namespace, cls: type[T], section: str, only: tuple[str, ...] = ()
) -> T:
    """``args.config``'s ``[section]`` (or the whole file) with ``args.overrides``, as ``cls``.

    ``only``: read just these keys of the section (``cls`` has just those fields), the rest
    unchecked: a one-shot command that needs a part of a node's config.
    """
    data: dict[str, Any] = load_toml(args.config) if args.config else {}
    if section in data and isinstance(data[section], dict):
        data = data[section]
    elif any(k in data for k in ("robot", "operator", "network", "scene")):
        data = {}
    prefix = f"{section}."
    local = [o[len(prefix) :] if o.startswith(prefix) else o for o in args.overrides]
    data = apply_overrides(data, local)
    if only:
        data = {k: v for k, v in data.items() if k in only}
    config = from_dict(cls, data, where=section)
    if args.config:
        check_secret_file(args.config, config)  # a token in a file others can read: refused
    return config


def print_config(config: Any, section: str) -> None:
    """The effective config, its secrets not shown (a terminal is often someone's screen)."""
    print(config_toml(config, section, redact=True), end="")


def reload_on_hangup(reload: threading.Event) -> None:
    """SIGHUP (systemd's ``ExecReload``) sets ``reload``; the process's loop acts on it."""
    if hasattr(signal, "SIGHUP"):
        on_signal(signal.SIGHUP, reload.set)


def write_stats(path: Path | None, stats: dict[str, Any]) -> None:
    if path is not None:
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(stats, indent=2, sort_keys=True))
        tmp.replace(path)


class Attachment(Protocol):
    def stop(self) -> None: ...


def freeze_startup_heap() -> int:
    """Exempt everything alive from the cyclic collector (``gc.freeze``); returns how many.

    A full collection walks every tracked object. With a node's stack loaded
    (NumPy, ZeroMQ, and on the robot numba and the model) that is over 100,000
    objects and tens of milliseconds (docs/benchmarks.md, Conditions): a stall
    in a 60 Hz loop whenever the collector decides to run. What is alive once
    the node is built lives as long as the process, so it is frozen and later
    collections walk only what the loop makes.

    No collection first: the node is built, its arm connected and the
    controller's watchdog armed, and a full collection holds the interpreter
    lock throughout (37 ms on a quiet machine with the robot's stack, longer
    when the process is preempted meanwhile), which stops the keep-alive's
    kicks too. :func:`run_node` collects before it builds instead; what the
    build left as garbage stays, once.
    """
    gc.freeze()
    return gc.get_freeze_count()


#: modules a node's threads would otherwise import mid-run, holding the interpreter lock while
#: the loop waits: NumPy loads ``numpy.ma`` on the first ``np.percentile`` (the status file's
#: latency summary), 12-17 ms with its bytecode at hand and 0.5 s where it must be compiled
#: (an environment with PYTHONDONTWRITEBYTECODE), which lifted a demo's palm 2 s in
LAZY_MODULES = ("numpy.ma",)


def import_lazy_modules() -> None:
    """Import ``LAZY_MODULES`` now, before the loop runs."""
    for name in LAZY_MODULES:
        importlib.import_module(name)


def bound_endpoints(*parts: Any) -> dict[str, Any]:
    """What each part bound or serves (its ``endpoints()``), for the node's READY=1."""
    out: dict[str, Any] = {}
    for part in parts:
        endpoints = getattr(part, "endpoints", None)
        if callable(endpoints):
            out.update(endpoints())
    return out


def run_node(
    args: argparse.Namespace,
    cls: type[T],
    section: str,
    build: Callable[[T, Any], Any],
    attach: Callable[[Any, T], Attachment | None] | None = None,
) -> int:
    """What both node commands do: config, optional recording, systemd, run, counters.

    ``build(config, recorder)`` makes the node (imported lazily by the caller,
    so ``--help`` loads nothing heavy); ``attach(node, config)`` may start
    something beside it (the dashboard) and returns what to stop afterwards.
    """
    config = load_node_config(args, cls, section)
    if args.print_config:
        print_config(config, section)
        return 0
    recorder = None
    if getattr(args, "record", None):
        from common.recording.mcap_recorder import node_recorder  # mcap only when recording

        recorder = node_recorder(args.record, config, section)
    stop = stop_on_signals()
    import_lazy_modules()
    # no collection from here until the heap is frozen: the devices connect during the build
    # (freeze_startup_heap); what the imports so far left goes now
    gc.collect()
    gc.disable()
    try:
        try:
            node = build(config, recorder)
            reload = getattr(node, "roster_reload", None)  # the robot's, with a roster
            if reload is not None:
                reload_on_hangup(reload)
            extra = attach(node, config) if attach is not None else None
            # READY=1 once the loop runs, with what the node and its attachments bound;
            # WATCHDOG=1 while it runs
            watch = watch_node(node, stop, endpoints=lambda: bound_endpoints(node, extra))
            frozen = freeze_startup_heap()
        finally:
            gc.enable()
        full_before = gc.get_stats()[2]["collections"]
        try:
            node.run(stop, args.duration)
        finally:
            watch.stop()
            if extra is not None:
                extra.stop()
            stats = node.stats()
            stats["gc_frozen_objects"] = float(frozen)
            stats["gc_full_collections"] = float(gc.get_stats()[2]["collections"] - full_before)
            write_stats(args.stats_file, stats)
    finally:
        if recorder is not None:
            recorder.close()
    return 0
