"""The tactile contract's values are pinned, and declared in ``common.tactile`` only."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from common import tactile

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("common", "robot_side", "operator_side", "deploy")
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


def test_no_module_declares_its_own_copy():
    copies = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if path == ROOT / "common" / "tactile.py":
                continue
            for node in ast.parse(path.read_text(), str(path)).body:
                if isinstance(node, ast.Assign):
                    targets, value = node.targets, node.value
                elif isinstance(node, ast.AnnAssign) and node.value is not None:
                    targets, value = [node.target], node.value
                else:
                    continue
                names = {t.id for t in targets if isinstance(t, ast.Name)}
                if names & CONTRACT_NAMES and _literal(value):
                    copies.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not copies, f"declare these in common/tactile.py and import them: {copies}"


def test_importers_share_the_contracts_objects():
    from common import codec
    from operator_side.dashboard import server
    from robot_side.gripper import base
    from robot_side.perception import inference, numba_forward
    from robot_side.tactile import script, synthetic

    assert codec.N_PATTERNS is tactile.N_PATTERNS
    assert server.GRIP_LEVELS is tactile.GRIP_LEVELS
    assert base.N_GRIP_LEVELS == script.N_GRIP_LEVELS == synthetic.N_GRIP_LEVELS == 31
    assert synthetic.FRAME_SHAPE is tactile.FRAME_SHAPE
    assert inference.SATURATION_N is tactile.SATURATION_N
    assert float(numba_forward._NINTH) == float(np.float32(1.0 / 9.0))
    assert float(numba_forward._PEAK_FLOOR) == 1.0
