"""The tactile contract's values are pinned, and declared in ``common.tactile.contract`` only."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from common.tactile import contract as tactile

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("common", "robot_side", "operator_side", "router_side", "deploy", "harness")
#: names that once had a literal copy in several modules
CONTRACT_NAMES = {
    "ANGLES_DEG",
    "CONTACT_FLOOR_N",
    "CONTACT_THRESHOLD_N",
    "FRAME_SHAPE",
    "GRIP_LEVELS",
    "MASKS",
    "N_ANGLES",
    "N_GRIP_LEVELS",
    "N_PATTERNS",
    "N_POSITIONS",
    "PEAK_FLOOR_N",
    "SATURATION_N",
    "SENSOR_MAX_N",
    "STIMULUS_MAX_N",
}


def test_values_are_the_papers():
    assert tactile.FRAME_SHAPE == (2, 10, 10)
    assert tactile.PAD_SHAPE == (10, 10)
    assert tactile.STIMULUS_SHAPE == (3, 3)
    assert tactile.SATURATION_N == 9.0
    assert tactile.CONTACT_FLOOR_N == 1.0
    assert tactile.ANGLES_DEG == (0, 45, 90, 135)
    assert (tactile.N_ANGLES, tactile.N_POSITIONS, tactile.N_PATTERNS) == (4, 3, 12)
    assert tactile.N_GRIP_LEVELS == 31
    assert list(tactile.GRIP_LEVELS) == list(range(1, 32))


def test_masks_are_pinned():
    expected = {
        0: {(1, 1)},
        1: {(0, 1)},
        2: {(2, 1)},
        3: {(0, 2), (1, 1), (2, 0)},
        4: {(0, 1), (1, 0)},
        5: {(1, 2), (2, 1)},
        6: {(0, 1), (1, 1), (2, 1)},
        7: {(0, 0), (1, 0), (2, 0)},
        8: {(0, 2), (1, 2), (2, 2)},
        9: {(0, 0), (1, 1), (2, 2)},
        10: {(1, 0), (2, 1)},
        11: {(0, 1), (1, 2)},
    }
    assert tactile.MASKS.shape == (12, 3, 3) and tactile.MASKS.dtype == bool
    for pattern, cells in expected.items():
        assert {tuple(map(int, rc)) for rc in np.argwhere(tactile.MASKS[pattern])} == cells
        # at most one cell per row: the codec refuses anything else on the wire
        assert tactile.MASKS[pattern].sum(axis=1).max() == 1
    np.testing.assert_array_equal(tactile.MASKS_F32, tactile.MASKS.astype(np.float32))
    assert not tactile.MASKS.flags.writeable and not tactile.MASKS_F32.flags.writeable


def test_pattern_numbering():
    assert [tactile.pattern_of(*tactile.classes_of(p)) for p in range(12)] == list(range(12))
    assert tactile.classes_of(7) == (2, 1)
    assert tactile.pattern_name(1) == "0 deg up"
    assert tactile.pattern_name(11) == "135 deg right"


def _literal(node: ast.expr) -> bool:
    """A value spelled out in the source: a number, a tuple of them, a range of them."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float))
    if isinstance(node, ast.Tuple):
        return all(_literal(e) for e in node.elts)
    if isinstance(node, ast.BinOp):
        return _literal(node.left) and _literal(node.right)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
        return node.func.id == "range" and all(_literal(a) for a in node.args)
    return False


def _own_copies(tree: ast.Module) -> list[int]:
    """Lines where a module assigns a contract name a value spelled out in numbers."""
    lines = []
    for node in tree.body:
        if isinstance(node, ast.Assign):
            targets, value = node.targets, node.value
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            targets, value = [node.target], node.value
        else:
            continue
        names = {t.id for t in targets if isinstance(t, ast.Name)}
        if names & CONTRACT_NAMES and _literal(value):
            lines.append(node.lineno)
    return lines


@pytest.fixture(scope="module")
def scanned() -> dict[str, list[str]]:
    """Both scans below over every project module but the contract's own, each parsed once.

    Only the findings are kept: a module's syntax tree is dropped once scanned (all of
    them held would be millions of objects for the garbage collector in every later test).
    """
    copies: list[str] = []
    spelled: list[str] = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if path in (ROOT / "common/tactile/contract.py", ROOT / "common/tactile/scale.py"):
                continue  # the contract, and its force scale apart from NumPy
            tree = ast.parse(path.read_text(), str(path))
            where = path.relative_to(ROOT)
            copies += [f"{where}:{n}" for n in _own_copies(tree)]
            spelled += [f"{where}:{n}: {what}" for n, what in _spelled_out(tree)]
    return {"copies": copies, "spelled": spelled}


def test_no_module_declares_its_own_copy(scanned):
    copies = scanned["copies"]
    assert not copies, f"declare these in common/tactile/contract.py and import them: {copies}"


def _spelled_out(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, what) for every place ``tree`` spells the contract out instead of naming it.

    A pattern encoded by hand (``3 * angle + position``, also with
    ``N_POSITIONS`` for the 3) or decoded (``divmod(p, 3)``), the frame's
    shape as numbers (``(2, 10, 10)``, ``reshape(2, 10, 10)``, ``(n, 2, 10, 10)``),
    and the patterns counted as ``range(12)``.
    """
    found = []

    def number(node: ast.AST, value: int) -> bool:
        return isinstance(node, ast.Constant) and type(node.value) is int and node.value == value

    def three(node: ast.AST) -> bool:
        return number(node, 3) or (isinstance(node, ast.Name) and node.id == "N_POSITIONS")

    def terms(node: ast.AST) -> list[ast.AST]:
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
            return terms(node.left) + terms(node.right)
        return [node]

    def shape(values: list[ast.AST]) -> bool:
        tail = values[-3:]
        return len(tail) == 3 and all(number(v, n) for v, n in zip(tail, (2, 10, 10), strict=True))

    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
            parts = terms(node)
            scaled = [
                t
                for t in parts
                if isinstance(t, ast.BinOp)
                and isinstance(t.op, ast.Mult)
                and (three(t.left) or three(t.right))
            ]
            rest = [t for t in parts if t not in scaled and not isinstance(t, ast.Constant)]
            if scaled and rest:
                found.append((node.lineno, "a pattern encoded by hand: use pattern_of"))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            name, args = node.func.id, node.args
            if name == "divmod" and len(args) == 2 and three(args[1]):
                found.append((node.lineno, "a pattern decoded by hand: use classes_of"))
            elif name == "range" and len(args) == 1 and number(args[0], 12):
                found.append((node.lineno, "range(12): use range(N_PATTERNS)"))
        as_tuple = isinstance(node, ast.Tuple) and shape(node.elts)
        as_arguments = isinstance(node, ast.Call) and len(node.args) == 3 and shape(node.args)
        if as_tuple or as_arguments:
            found.append((node.lineno, "the frame's shape as numbers: use FRAME_SHAPE"))
    # an encoding inside another (CELLS + 3 * r + c) is reported once per line
    return sorted(set(found))


def test_the_scan_finds_each_spelled_out_form():
    """The scan below is only as good as what it recognises: each form, and the look-alikes."""
    caught = """
pattern = 3 * angle + position
pattern = position + 3 * int(angle)
pattern = angle * N_POSITIONS + position
cells[CELLS + 3 * r + c] = 1
angle, position = divmod(pattern, 3)
for p in range(12): pass
zero = np.zeros((2, 10, 10), np.float32)
batch = np.zeros((n, 2, 10, 10))
frame = out.reshape(2, 10, 10)
"""
    for line in caught.strip().splitlines():
        assert _spelled_out(ast.parse(line)), line
    passed = """
length = 3 * n + 4
offset = 8 + 3 * k
timeout = 1.0 + 3 * frames / 120
loop, rest = divmod(t, period)
pattern = pattern_of(angle, position)
for p in range(N_PATTERNS): pass
cells[_COLS * r + c] = 1
shape = (3, 10, 10)
"""
    for line in passed.strip().splitlines():
        assert not _spelled_out(ast.parse(line)), line


def test_no_module_spells_the_contract_out(scanned):
    """``grep`` for the encoding finds it in common/tactile/contract.py only (and in the tests)."""
    spelled = scanned["spelled"]
    assert not spelled, "name the contract (common/tactile/contract.py) instead:\n" + "\n".join(
        spelled
    )


def test_importers_share_the_contracts_objects():
    from common.wire import codec_schema
    from operator_side.dashboard import page_commands
    from robot_side.gripper import base
    from robot_side.perception import numba_forward, numpy_forward
    from robot_side.tactile import script

    assert codec_schema.N_PATTERNS is tactile.N_PATTERNS
    assert page_commands.GRIP_LEVELS is tactile.GRIP_LEVELS
    assert base.N_GRIP_LEVELS == script.N_GRIP_LEVELS == 31
    assert numpy_forward.SATURATION_N is tactile.SATURATION_N
    assert float(numba_forward._NINTH) == float(np.float32(1.0 / 9.0))
    assert float(numba_forward._PEAK_FLOOR) == 1.0
