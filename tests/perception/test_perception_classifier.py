"""The shipped model: it loads, meets the accuracy bar, and every backend agrees."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from independent_generator import spec_set

from robot_side.perception import (
    BACKENDS,
    DEFAULT_MODEL,
    ModelLoadError,
    TiltClassifier,
    load_classifier,
)
from robot_side.perception import dataset as ds

#: a fresh synthetic test set: seeds the shipped model never trained on
TEST_SEED = 20_261_122


@pytest.fixture(scope="module")
def fresh() -> ds.TactileDataset:
    return ds.generate(ds.DatasetConfig(repeats=6, seed=TEST_SEED))  # 2,232 frames


@pytest.fixture(scope="module")
def numpy_classifier() -> TiltClassifier:
    return load_classifier(backend="numpy")


@pytest.fixture(scope="module")
def reference() -> TiltClassifier:
    pytest.importorskip("torch")
    return load_classifier(backend="torch")


def test_shipped_files_are_in_the_package_and_small() -> None:
    for suffix in (".npz", ".onnx", ".report.json", ".report.png"):
        path = DEFAULT_MODEL.with_name(DEFAULT_MODEL.stem + suffix)
        assert path.is_file(), path
    total = sum(p.stat().st_size for p in DEFAULT_MODEL.parent.iterdir() if p.is_file())
    assert total < 4 * 2**20


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
def test_shipped_model_meets_the_bar_on_fresh_synthetic_frames(
    numpy_classifier: TiltClassifier, fresh: ds.TactileDataset
) -> None:
    angle, position = numpy_classifier.predict(fresh.frames)
    assert angle.dtype == np.int64 and angle.shape == (len(fresh),)
    assert (angle == fresh.angle).mean() >= 0.98
    assert (position == fresh.position).mean() >= 0.97
    for level in (1, 16, 31):  # the lightest and the strongest grips too
        sel = fresh.grip_level == level
        assert (angle[sel] == fresh.angle[sel]).mean() >= 0.95, level
        assert (position[sel] == fresh.position[sel]).mean() >= 0.93, level


def test_shipped_model_carries_over_to_an_independent_generator(
    numpy_classifier: TiltClassifier,
) -> None:
    frames, angle, position = spec_set(repeats=2, seed=5)
    pa, pp = numpy_classifier.predict(frames)
    assert (pa == angle).mean() >= 0.95
    assert (pp == position).mean() >= 0.93


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != "torch"])
def test_backends_match_eager_torch(
    backend: str, reference: TiltClassifier, fresh: ds.TactileDataset
) -> None:
    pytest.importorskip({"onnxruntime": "onnxruntime", "numba": "numba"}.get(backend, "numpy"))
    edge = np.stack(
        [
            np.zeros((2, 10, 10)),  # nothing grasped
            np.full((2, 10, 10), 9.0),  # everything saturated
            np.pad(np.full((2, 1, 1), 1.0), ((0, 0), (4, 5), (4, 5))),  # one taxel at the floor
        ]
    ).astype(np.float32)
    frames = np.concatenate([edge, fresh.frames[:500]])
    clf = load_classifier(backend=backend)
    assert clf.backend == backend
    ra, rp = reference.predict_proba(frames)
    a, p = clf.predict_proba(frames)
    assert a.shape == (len(frames), 4) and p.shape == (len(frames), 3)
    np.testing.assert_allclose(a, ra, atol=1e-5)
    np.testing.assert_allclose(p, rp, atol=1e-5)
    ca, cp = clf.predict(frames)
    ta, tp = reference.predict(frames)
    assert np.array_equal(ca, ta) and np.array_equal(cp, tp)
    # batch 1, the robot node's case, through the preallocated path
    for i in range(20):
        one = frames[i : i + 1]
        ba, bp = clf.predict_proba(one)
        np.testing.assert_allclose(ba, ra[i : i + 1], atol=1e-5)
        np.testing.assert_allclose(bp, rp[i : i + 1], atol=1e-5)
        assert clf.predict(one)[0][0] == ta[i] and clf.predict(frames[i])[1][0] == tp[i]


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
@pytest.mark.parametrize("backend", BACKENDS)
def test_one_frame_at_a_time_agrees_with_the_batch_path(
    backend: str, fresh: ds.TactileDataset
) -> None:
    """predict_one (the robot node's call) gives predict's classes and predict_proba's odds."""
    pytest.importorskip(
        {"numpy": "numpy", "onnxruntime": "onnxruntime", "numba": "numba"}.get(backend, "torch")
    )
    clf = load_classifier(backend=backend)
    edge = [np.zeros((1, 2, 10, 10), np.float32), np.full((1, 2, 10, 10), 9.0, np.float32)]
    frames = np.concatenate([*edge, fresh.frames[:200]])
    ca, cp = clf.predict(frames)
    pa, pp = clf.predict_proba(frames)
    for i, frame in enumerate(frames):
        one = clf.predict_one(frame)
        assert (one.angle, one.position) == (ca[i], cp[i])
        assert one.pattern == 3 * ca[i] + cp[i]
        np.testing.assert_allclose(one.angle_probs, pa[i], atol=1e-6)
        np.testing.assert_allclose(one.position_probs, pp[i], atol=1e-6)
        assert 0.0 <= one.confidence <= 1.0
    # float64 in, or a read-only array, is taken as is; a wrong shape is named
    assert clf.predict_one(frames[5].astype(np.float64)).pattern == 3 * ca[5] + cp[5]
    with pytest.raises(ValueError, match=r"\(2, 10, 10\)"):
        clf.predict_one(frames[:1])


def test_probabilities_are_distributions(numpy_classifier: TiltClassifier) -> None:
    frames = np.random.default_rng(0).uniform(0, 9, (50, 2, 10, 10)).astype(np.float32)
    a, p = numpy_classifier.predict_proba(frames)
    assert a.dtype == np.float32
    np.testing.assert_allclose(a.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-6)
    assert np.array_equal(a.argmax(1), numpy_classifier.predict(frames)[0])


def test_wrong_frame_shapes_are_refused(numpy_classifier: TiltClassifier) -> None:
    with pytest.raises(ValueError, match=r"\(N, 2, 10, 10\)"):
        numpy_classifier.predict(np.zeros((1, 10, 10, 2), np.float32))


@pytest.mark.slow
@pytest.mark.untimed  # no timing checked
def test_non_torch_backends_do_not_import_torch() -> None:
    code = (
        "import sys, numpy as np\n"
        "from robot_side.perception import load_classifier\n"
        "for b in ('numba', 'numpy', 'onnxruntime'):\n"
        "    load_classifier(backend=b).predict(np.zeros((1, 2, 10, 10), np.float32))\n"
        "default = load_classifier()\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "print(default.backend)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() in ("numba", "numpy", "onnxruntime")


def test_unusable_models_raise_model_load_error(tmp_path: Path) -> None:
    with pytest.raises(ModelLoadError, match="does not exist"):
        load_classifier(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ModelLoadError, match="not a readable"):
        load_classifier(tmp_path / "junk.npz")
    np.savez(tmp_path / "nometa.npz", a=np.zeros(3))
    with pytest.raises(ModelLoadError, match="meta"):
        load_classifier(tmp_path / "nometa.npz")
    with pytest.raises(ModelLoadError, match="unknown backend"):
        load_classifier(backend="tensorflow")
    weights_only = tmp_path / "w.npz"
    weights_only.write_bytes(DEFAULT_MODEL.read_bytes())
    with pytest.raises(ModelLoadError, match="ONNX"):
        load_classifier(weights_only, backend="onnxruntime")
    # the default falls back to a backend that needs only the weights
    assert load_classifier(weights_only).backend in ("numba", "numpy")


def test_a_default_backend_that_fails_to_load_gives_way_to_the_next(monkeypatch, caplog) -> None:
    pytest.importorskip("numba")
    from robot_side.perception import numba_forward

    def broken(*args, **kwargs):
        raise RuntimeError("LLVM ERROR: out of registers")

    monkeypatch.setattr(numba_forward, "NumbaForward", broken)
    with pytest.raises(ModelLoadError, match="numba backend failed to compile"):
        load_classifier(backend="numba")
    clf = load_classifier()
    assert clf.backend != "numba"
    assert "numba unusable" in caplog.text
