"""One way to run a process: ``deploy/units`` spawns, stops and reads readiness, and nothing
else does (issue 55).

Every process the demo, the fault matrix, the fleet, the soak and the bench
start is spawned with :func:`deploy.units.process.spawn`, stopped with
:func:`deploy.units.process.stop` and known to be up by its ``READY=1``
(:mod:`deploy.units.readiness`). This test reads the tree and fails on:

- a second copy of spawn or stop, by name (a function called ``spawn_cli``,
  ``stop_process``, ``stop_child`` ... outside ``deploy/units``) or by shape
  (a ``proc.wait(timeout=...)`` followed by SIGKILL or ``proc.kill()`` of the
  process it waited for, in one function);
- readiness read from log text or files in ``deploy/`` and ``harness/``: a
  ready file (``--ready-file``, ``ready_file``), an "up" line searched for in
  a log (``"node up" in proc.log_text()``, ``line.startswith('{"simulator"')``),
  a ``ready`` line on stdout (``line == "ready"``), a file polled until it
  exists (``while not path.exists()``).

Tests may read logs for what a process said (an assertion about content);
``tests/`` is not scanned.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: where a second spawn or stop must not be: the product and the harness
PACKAGES = ("common", "robot_side", "operator_side", "router_side", "deploy", "harness")
#: where readiness must come from READY=1: what starts processes
STARTERS = ("deploy", "harness")
MODEL = Path("deploy/units")

#: names of the one model's functions: another function so called is a second copy
MODEL_NAMES = frozenset(
    {
        "spawn",
        "spawn_cli",
        "spawn_child",
        "spawn_process",
        "cli_argv",
        "die_with_parent",
        "stop_process",
        "stop_child",
        "kill_process",
        "terminate",
    }
)

#: a child of the product's own that may not use deploy.units (the import direction), with
#: why; the list only shrinks
OWN_CHILDREN: dict[str, str] = {
    "robot_side/devices/stdio_child.py": (
        "the robot node's device process (the lab world over stdio) is the node's own "
        "child, and robot_side may not import deploy"
    ),
}

#: what a process says when it is up, as a line of its log or its stdout
UP_TEXT = re.compile(r"(\bup\b|\bready\b|listening|signalling at|\{\"simulator\")", re.I)
LOG_READERS = frozenset({"log_text", "read_text", "read_bytes", "readline", "readlines"})


def _functions(tree: ast.AST) -> list[ast.FunctionDef | ast.AsyncFunctionDef]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]


def _called(node: ast.AST) -> str | None:
    """The name a call calls (``stop`` for ``x.stop(...)`` and ``stop(...)``)."""
    if not isinstance(node, ast.Call):
        return None
    func = node.func
    return func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)


#: what a function that starts or stops a process touches
PROCESS_WORDS = frozenset(
    {"Popen", "send_signal", "kill", "killpg", "terminate", "SIGTERM", "SIGKILL", "SIGINT"}
)


def _touches_processes(fn: ast.AST) -> bool:
    return any(
        (isinstance(n, ast.Attribute) and n.attr in PROCESS_WORDS)
        or (isinstance(n, ast.Name) and n.id in PROCESS_WORDS)
        for n in ast.walk(fn)
    )


def second_copies(path: Path, tree: ast.AST) -> list[str]:
    """``path:line: why`` for each spawn or stop of this file's own."""
    found = []
    top = {id(n) for n in getattr(tree, "body", [])}
    for fn in _functions(tree):
        named = fn.name.lstrip("_") in MODEL_NAMES
        if named and (id(fn) in top or _touches_processes(fn)):  # not a thread's "spawn"
            found.append(f"{path}:{fn.lineno}: a function named {fn.name}")
        waited: dict[str, int] = {}  # what was waited for -> the first such wait's line
        for n in ast.walk(fn):
            if (
                _called(n) == "wait"
                and isinstance(n.func, ast.Attribute)
                and any(k.arg == "timeout" for k in n.keywords)
            ):
                who = ast.unparse(n.func.value)
                waited[who] = min(waited.get(who, n.lineno), n.lineno)
        if not waited:
            continue
        first = min(waited.values())
        # the process waited for, then killed (a load generator beside it is no stop)
        killed = [
            n.lineno
            for n in ast.walk(fn)
            if _called(n) == "kill"
            and isinstance(n.func, ast.Attribute)
            and ast.unparse(n.func.value) in waited
        ]
        # or SIGKILL sent, however
        killed += [
            n.lineno
            for n in ast.walk(fn)
            if (isinstance(n, ast.Attribute) and n.attr == "SIGKILL")
            or (isinstance(n, ast.Name) and n.id == "SIGKILL")
        ]
        if any(k > first for k in killed):
            found.append(f"{path}:{fn.lineno}: {fn.name} waits, then kills (a stop of its own)")
    return found


def _reads_a_log(node: ast.AST, tainted: frozenset[str] = frozenset()) -> bool:
    """Whether ``node`` reads a log, or a name the function set from one."""
    return any(
        _called(n) in LOG_READERS or (isinstance(n, ast.Name) and n.id in tainted)
        for n in ast.walk(node)
    )


def _log_names(tree: ast.AST) -> dict[int, frozenset[str]]:
    """Line -> the names set from a log read in the function around that line."""
    out: dict[int, frozenset[str]] = {}
    for fn in _functions(tree):
        names = frozenset(
            t.id
            for n in ast.walk(fn)
            if isinstance(n, ast.Assign) and _reads_a_log(n.value)
            for t in n.targets
            if isinstance(t, ast.Name)
        )
        for n in ast.walk(fn):
            if hasattr(n, "lineno"):
                out[n.lineno] = out.get(n.lineno, frozenset()) | names
    return out


def readiness_from_text(path: Path, tree: ast.AST, source: str) -> list[str]:
    """``path:line: why`` for each readiness read from a log, a line or a file."""
    found = []
    for line_no, line in enumerate(source.splitlines(), 1):
        if re.search(r"ready[-_]file", line):
            found.append(f"{path}:{line_no}: a ready file")
    tainted = _log_names(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            texts = [
                c.value
                for c in (node.left, *node.comparators)
                if isinstance(c, ast.Constant) and isinstance(c.value, str)
            ]
            said = [t for t in texts if UP_TEXT.search(t)]
            reads = _reads_a_log(node, tainted.get(node.lineno, frozenset()))
            if said and any(isinstance(op, ast.In) for op in node.ops) and reads:
                found.append(f"{path}:{node.lineno}: {said[0]!r} searched for in a log")
            if any(t.strip() in ("ready", "joined") for t in texts) and any(
                isinstance(op, ast.Eq | ast.NotEq) for op in node.ops
            ):
                found.append(f"{path}:{node.lineno}: a {texts[0]!r} line read as readiness")
        if (
            _called(node) == "startswith"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
            and UP_TEXT.search(node.args[0].value)
        ):
            found.append(f"{path}:{node.lineno}: a line starting {node.args[0].value!r}")
        if (
            isinstance(node, ast.While)
            and isinstance(node.test, ast.UnaryOp)
            and isinstance(node.test.op, ast.Not)
            and _called(node.test.operand) == "exists"
        ):
            found.append(f"{path}:{node.lineno}: a file polled until it exists")
    return found


def _sources(packages: tuple[str, ...]):
    for package in packages:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT)
            if rel.is_relative_to(MODEL):
                continue
            source = path.read_text()
            yield rel, ast.parse(source, str(rel)), source


def test_spawn_and_stop_exist_once():
    found = [
        f
        for rel, tree, _ in _sources(PACKAGES)
        if str(rel) not in OWN_CHILDREN
        for f in second_copies(rel, tree)
    ]
    assert not found, (
        "a second way to start or stop a process; use deploy.units.process.spawn / stop "
        "(or deploy.units.service.Service):\n" + "\n".join(found)
    )


def test_the_allowed_own_children_are_still_there_and_still_need_it():
    """An entry whose file is gone, or no longer has a stop of its own, is deleted."""
    for rel, why in OWN_CHILDREN.items():
        path = ROOT / rel
        assert path.exists(), f"{rel} is gone: delete its entry ({why})"
        assert second_copies(Path(rel), ast.parse(path.read_text())), (
            f"{rel} no longer stops a process of its own: delete its entry"
        )


def test_readiness_comes_from_ready_1_only():
    found = [
        f
        for rel, tree, source in _sources(STARTERS)
        for f in readiness_from_text(rel, tree, source)
    ]
    assert not found, (
        "readiness read from log text or a file; wait for the child's READY=1 "
        "(deploy.units: Service.wait_ready, NotifySocket.wait_ready):\n" + "\n".join(found)
    )


# ------------------------------------------------------------------ the checks themselves
_OLD_SHAPES = {
    # deploy/demo.py and harness/processes.py before issue 55
    "def spawn_cli(args, log_path):\n    return subprocess.Popen(args)\n": "named spawn_cli",
    "def stop_child(proc):\n    proc.terminate()\n    proc.wait()\n": "named stop_child",
    (
        "def halt(proc):\n    proc.send_signal(15)\n    try:\n        proc.wait(timeout=10)\n"
        "    except TimeoutExpired:\n        proc.kill()\n"
    ): "waits, then kills",
    (
        "def halt(proc):\n    proc.wait(timeout=10)\n    os.kill(proc.pid, signal.SIGKILL)\n"
    ): "waits, then kills",
}

_OLD_READINESS = {
    'def f(op):\n    wait_for(lambda: "operator node up" in op.log_text())\n': "in a log",
    "def f(proc):\n    for line in proc.log_text().splitlines():\n"
    "        if line.startswith('{\"simulator\"'):\n            return line\n": "a line starting",
    'args = ["--ready-file", str(ready)]\n': "a ready file",
    'def f(proc):\n    if proc.stdout.readline().strip() == "ready":\n        pass\n': "line read",
    "def f(path):\n    while not path.exists():\n        time.sleep(0.1)\n": "polled",
    (
        "def f(log_path):\n    text = log_path.read_bytes().decode()\n"
        "    if '{\"simulator\"' in text:\n        pass\n"
    ): "in a log",
}


def test_the_checks_find_what_the_tree_had_before():
    for source, why in _OLD_SHAPES.items():
        found = second_copies(Path("x.py"), ast.parse(source))
        assert found and why in found[0], (source, found)
    for source, why in _OLD_READINESS.items():
        found = readiness_from_text(Path("x.py"), ast.parse(source), source)
        assert found and why in found[0], (source, found)


def test_the_one_model_passes_its_own_checks():
    """What deploy.units itself does (a SIGKILL after its wait) is the one copy."""
    path = ROOT / "deploy/units/process.py"
    assert second_copies(Path("process.py"), ast.parse(path.read_text()))
