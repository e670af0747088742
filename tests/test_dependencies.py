"""What the code imports is what pyproject.toml declares, in the group of the machine that runs it.

A package the product imports but no group declares installs on the development machine (its
`.[all]` pulls it in through another package) and is missing on a robot PC; a package declared
but never imported is weight on every install. The robot PC's group stays free of PyTorch and
ONNX: the robot node classifies on numba (ONNX Runtime, then NumPy, where numba is missing),
and the robot node runs with them unimportable.
"""

from __future__ import annotations

import ast
import functools
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

# reading every module of the product, the tests and the scripts takes seconds; no timing checked
pytestmark = [pytest.mark.slow, pytest.mark.untimed]

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
#: the product's packages (setuptools' include list, without its globs)
PRODUCT = sorted(
    p.rstrip("*") for p in PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
)
BASE = "(base)"

#: an import name whose distribution is named otherwise
IMPORT_TO_DIST = {
    "cv2": "opencv-python",
    "google": "protobuf",  # google.protobuf
    "nacl": "pynacl",
    "rtde_control": "ur-rtde",
    "rtde_receive": "ur-rtde",
    "scservo_sdk": "feetech-servo-sdk",
    "serial": "pyserial",
    "xdist": "pytest-xdist",
    "yaml": "PyYAML",
    "zenoh": "eclipse-zenoh",
    "zmq": "pyzmq",
    "foxglove": "foxglove-sdk",
    "foxglove_schemas_protobuf": "foxglove-schemas-protobuf",
}

#: imported only by tests that run in an environment of their own (tests/export/lerobot_env.py
#: makes it: LeRobot's own loader, pinned apart from the project's torch)
OWN_ENVIRONMENT = {"lerobot", "ledataset"}

#: declared without an import of that name: what a declared package needs at run time
#: (torch.onnx.export needs onnx) or a tool run as a command
DECLARED_UNIMPORTED = {
    "onnx": "torch.onnx.export writes the model's .onnx with it (deepxpalm train)",
    "pytest-timeout": "a pytest plugin (pyproject's timeout setting)",
    "ruff": "the linter, run as a command (make lint)",
}


def _norm(name: str) -> str:
    """PEP 503: the name pip compares."""
    return re.sub(r"[-_.]+", "-", name).lower()


def _dist(requirement: str) -> str:
    return _norm(re.split(r"[\s<>=!~;\[(]", requirement.strip(), maxsplit=1)[0])


def groups() -> dict[str, set[str]]:
    """group -> the distributions it installs (``deepxpalm[x]`` resolved to x's), base included."""
    project = PYPROJECT["project"]
    raw = {BASE: project["dependencies"], **project["optional-dependencies"]}

    def resolve(name: str, seen: frozenset[str] = frozenset()) -> set[str]:
        out: set[str] = set()
        for req in raw[name]:
            if _dist(req) == "deepxpalm":
                inner = req[req.index("[") + 1 : req.index("]")]
                for extra in inner.split(","):
                    if extra.strip() not in seen:
                        out |= resolve(extra.strip(), seen | {name})
            else:
                out.add(_dist(req))
        return out

    return {name: resolve(name) for name in raw}


#: calls that import (or look for) the module their first argument names
IMPORTING_CALLS = {"import_module", "importorskip", "find_spec"}


@functools.cache
def _imports(path: Path) -> frozenset[str]:
    """Top-level names of every absolute import in ``path``, in functions too, and of the
    modules named to ``importlib.import_module``, ``find_spec`` and ``pytest.importorskip``."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name.partition(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module.partition(".")[0])
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            first = node.args[0]
            if isinstance(first, ast.JoinedStr) and first.values:  # f"pkg.{name}"
                first = first.values[0]
            if (
                called in IMPORTING_CALLS
                and isinstance(first, ast.Constant)
                and isinstance(first.value, str)
                and not first.value.startswith(".")
            ):
                found.add(first.value.partition(".")[0])
    return frozenset(n for n in found if n.isidentifier())


def third_party(folders: list[str], local: set[str] = frozenset()) -> dict[str, set[str]]:
    """distribution -> the files under ``folders`` that import it."""
    first_party = set(PRODUCT) | set(local)
    out: dict[str, set[str]] = {}
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for name in _imports(path):
                if name in sys.stdlib_module_names or name in first_party or name == "__future__":
                    continue
                dist = _norm(IMPORT_TO_DIST.get(name, name))
                out.setdefault(dist, set()).add(str(path.relative_to(ROOT)))
    return out


def test_every_package_the_product_imports_is_declared() -> None:
    declared = set().union(*groups().values())
    missing = {d: sorted(f) for d, f in third_party(PRODUCT).items() if d not in declared}
    assert not missing, (
        "imported by the product but declared in no group of pyproject.toml "
        "(add it to the extra of the machine that runs it, or map its import name in "
        f"IMPORT_TO_DIST): {missing}"
    )


def test_every_package_the_tests_and_scripts_import_is_declared() -> None:
    local = {p.stem for p in (ROOT / "tests").rglob("*.py")} | {"tests"} | OWN_ENVIRONMENT
    declared = set().union(*groups().values())
    found = third_party(["tests", "scripts"], local)
    missing = {d: sorted(f) for d, f in found.items() if d not in declared}
    assert not missing, f"imported by tests or scripts but declared in no group: {missing}"


def test_every_declared_package_is_imported() -> None:
    """A group declares nothing the code does not import (tqdm was, after the bar moved)."""
    everything = third_party([*PRODUCT, "tests", "scripts"], {"tests"})
    declared = set().union(*groups().values()) - {"deepxpalm"}
    unused = sorted(d for d in declared if d not in everything and d not in DECLARED_UNIMPORTED)
    assert not unused, f"declared in pyproject.toml but imported nowhere: {unused}"


def test_the_groups_fit_their_machines() -> None:
    g = groups()
    assert not g["robot"] & {"torch", "onnx"}, "the robot PC never imports torch or onnx"
    assert {"torch", "onnx"} <= g["train"], "training needs torch and the ONNX export"
    assert not g["operator"] & {"torch", "onnx", "numba", "onnxruntime"}
    assert not g[BASE] & {"torch", "onnx", "numba", "onnxruntime", "tqdm"}
    # the CPU wheel the Makefile and the README install is one the range admits
    train_torch = next(r for r in PYPROJECT["project"]["optional-dependencies"]["train"] if
                       _dist(r) == "torch")  # fmt: skip
    assert re.fullmatch(r"torch>=2\.\d+,<3", train_torch), train_torch


def test_each_product_package_imports_only_what_its_machines_install() -> None:
    """The robot side needs no operator group, the operator side no robot group, and the
    router host (base and fabric) nothing else."""
    g = groups()
    # what may run where: the groups a package's modules may import from
    allowed = {
        "router_side": {BASE, "fabric"},
        "operator_side": {BASE, "operator", "fabric", "record", "foxglove", "study", "video"},
        "robot_side": {BASE, "robot", "fabric", "video", "train", "record", "dataset", "lab"},
    }
    wrong = {}
    for package, names in allowed.items():
        ok = set().union(*(g[n] for n in names))
        for dist, files in third_party([package]).items():
            if dist not in ok:
                wrong[dist] = sorted(files)
    assert not wrong, f"imported outside the groups of the machines that run them: {wrong}"


def test_the_robot_node_runs_without_torch_or_onnx(tmp_path: Path) -> None:
    """``deepxpalm robot`` (the scripted sensor, mask mode: the CNN classifies every frame) with
    every package the robot group does not install made unimportable."""
    blocked = ["torch", "onnx", "onnxscript", "matplotlib", "scipy", "pyarrow", "tqdm"]
    stats = tmp_path / "stats.json"
    code = (
        "import sys\n"
        f"for name in {blocked!r}:\n"
        "    sys.modules[name] = None  # import fails, find_spec says not installed\n"
        "from deploy.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    argv = [
        "robot",
        "--duration",
        "2",
        "--stats-file",
        str(stats),
        "--set",
        'robot.link.telemetry_endpoint="tcp://127.0.0.1:0"',
        "--set",
        'robot.link.command_endpoint="tcp://127.0.0.1:0"',
    ]
    out = subprocess.run(
        [sys.executable, "-c", code, *argv],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    counters = json.loads(stats.read_text())
    assert counters["inferences"] > 0, counters
