"""Classifying frames at 60 Hz: one interface, five backends of the same weights.

- ``numba``: the whole forward pass compiled to one function
  (``numba_forward``): a few kilobytes of loops behind one call, which is
  what a frame that meets cold caches needs.
- ``numpy``: a hand-written forward pass (batch norm folded into the
  convolutions, convolutions as one gather and one matrix product, both
  heads merged into block-diagonal matrices). No dependency beyond NumPy.
- ``onnxruntime``: the ``.onnx`` exported beside the weights.
- ``torch`` (eager) and ``torchscript``: the reference, and its traced,
  frozen form. Only these two import torch, which costs about 2 s.

Every backend returns the same classes and probabilities within 1e-5 of
eager torch (tests/perception). The default is the fastest of them on batch
1 when frames are paced as the sensor paces them, measured by ``deepxpalm
bench`` (docs/benchmarks.md): numba, then ONNX Runtime when numba is not
installed (or the ``.onnx`` is missing), then NumPy.

A classifier keeps preallocated buffers for batch 1, the robot node's case,
so one instance must not be used from two threads at once without a lock;
``predict`` takes an internal lock, which costs well under a microsecond.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.tactile.contract import (
    FRAME_SHAPE,
    N_ANGLES,
    N_POSITIONS,
    pattern_of,
)
from robot_side.perception.errors import ModelLoadError
from robot_side.perception.numpy_forward import Logits, NumpyForward
from robot_side.perception.weights import DEFAULT_MODEL, read_weights

log = logging.getLogger(__name__)

#: preference order when no backend is named: fastest measured first
DEFAULT_BACKEND_ORDER = ("numba", "onnxruntime", "numpy", "torchscript", "torch")


@dataclass(frozen=True, slots=True)
class Prediction:
    """One frame's classes and probabilities (plain floats: nine numbers need no NumPy)."""

    angle: int  # 0..3: 0, 45, 90, 135 deg
    position: int  # 0..2: centre, left (up for 0 deg), right (down for 0 deg)
    angle_probs: tuple[float, ...]
    position_probs: tuple[float, ...]

    @property
    def pattern(self) -> int:
        return pattern_of(self.angle, self.position)

    @property
    def confidence(self) -> float:
        """Probability of the pattern: both heads right, taken as independent."""
        return self.angle_probs[self.angle] * self.position_probs[self.position]


def _argmax_softmax(z: list[float]) -> tuple[int, tuple[float, ...]]:
    """Class (ties: the lowest, as NumPy's argmax) and softmax, in float64."""
    top = max(z)
    e = [math.exp(v - top) for v in z]
    total = sum(e)
    return z.index(top), tuple(v / total for v in e)


class TiltClassifier:
    """Angle and position classes of tactile frames.

    ``frames`` are float32 newtons of shape (N, 2, 10, 10) in the common view
    (a single ``FRAME_SHAPE`` frame is taken as N = 1). Angle classes 0..3 are 0,
    45, 90 and 135 deg; position classes 0..2 are centre, left (up for 0 deg)
    and right (down for 0 deg).
    """

    def __init__(
        self,
        logits_fn: Callable[[np.ndarray], Logits],
        backend: str,
        meta: dict,
        path: Path,
        logits_one: Callable[[np.ndarray], Logits] | None = None,
        classify_one: Callable[[np.ndarray], list[float]] | None = None,
    ):
        self._logits = logits_fn
        # one ``FRAME_SHAPE`` frame -> (4,) and (3,) logits, through preallocated buffers
        self._logits_one = logits_one or (lambda x: tuple(z[0] for z in logits_fn(x[None])))
        # a backend that also takes argmax and softmax: [angle, position, *probabilities]
        self._classify_one = classify_one
        self.backend = backend
        self.meta = meta
        self.path = path
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"TiltClassifier(backend={self.backend!r}, path={str(self.path)!r})"

    @property
    def numba_forward(self) -> Any:
        """The compiled pass (``NumbaForward``) with the numba backend, else None: the
        robot node folds it into its own compiled frame step (``robot_side.node.compiled_step``)."""
        return self._logits if self.backend == "numba" else None

    def logits(self, frames: np.ndarray) -> Logits:
        """Raw scores (N, 4) and (N, 3), float32."""
        x = _as_batch(frames)
        with self._lock:
            a, p = self._logits(x)
            return a.copy(), p.copy()

    def predict(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(angle class, position class), int64 arrays of shape (N,)."""
        x = _as_batch(frames)
        with self._lock:
            a, p = self._logits(x)
            return a.argmax(axis=1), p.argmax(axis=1)

    def predict_proba(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Softmax probabilities (N, 4) and (N, 3), float32."""
        x = _as_batch(frames)
        with self._lock:
            a, p = self._logits(x)
            return _softmax(a), _softmax(p)

    def predict_one(self, frame: np.ndarray) -> Prediction:
        """One ``FRAME_SHAPE`` frame: the robot node's hot path.

        The same classes as ``predict`` and probabilities within 1e-6 of
        ``predict_proba``. The frame goes straight into preallocated buffers
        and the seven logits come out as Python floats: a frame classified
        once per sensor period meets cold caches, where each NumPy call costs
        tens of microseconds, so the fewer calls the better.
        """
        x = frame
        if type(x) is not np.ndarray or x.dtype != np.float32 or x.shape != FRAME_SHAPE:
            x = np.asarray(frame, dtype=np.float32)
            if x.shape != FRAME_SHAPE:
                raise ValueError(f"a frame has shape {FRAME_SHAPE}, not {x.shape}")
        if self._classify_one is not None:
            with self._lock:
                r = self._classify_one(x)
            a = 2 + N_ANGLES
            return Prediction(int(r[0]), int(r[1]), tuple(r[2:a]), tuple(r[a:]))
        with self._lock:
            a, p = self._logits_one(x)
            a, p = a.tolist(), p.tolist()  # copies: the buffers are reused
        angle, angle_probs = _argmax_softmax(a)
        position, position_probs = _argmax_softmax(p)
        return Prediction(angle, position, angle_probs, position_probs)


def load_classifier(
    path: str | Path | None = None, backend: str | None = None, *, num_threads: int = 1
) -> TiltClassifier:
    """A classifier for the weights at ``path`` (default: the shipped model).

    ``backend`` is one of ``BACKENDS``; None picks the first usable one in
    ``DEFAULT_BACKEND_ORDER`` (installed, and for ONNX Runtime with its
    ``.onnx`` beside the weights). ``num_threads`` bounds ONNX Runtime's
    intra-op threads, and for the torch backends sets torch's process-wide
    thread count: one is fastest at batch 1 and leaves the other core to the
    rest of the node.
    """
    path = Path(path) if path is not None else DEFAULT_MODEL
    if backend is None:
        read_weights(path)  # a bad file fails here, by name, whatever the backend
        usable = [b for b in DEFAULT_BACKEND_ORDER if _usable(b, path)]
        for b in usable[:-1]:  # a backend that fails to load gives way to the next
            try:
                return load_classifier(path, b, num_threads=num_threads)
            except ModelLoadError as e:
                log.warning("classifier backend %s unusable (%s); trying the next", b, e)
        backend = usable[-1]
    if backend not in BACKEND_TABLE:
        raise ModelLoadError(f"unknown backend {backend!r}; choose one of {list(BACKENDS)}")
    if not backend_installed(backend):
        module = BACKEND_TABLE[backend].module
        extra = "train" if module == "torch" else "robot"  # the robot PC never installs torch
        raise ModelLoadError(
            f"backend {backend!r} needs the Python package {module!r}, which is not "
            f"installed: install the {extra} extra (pip install 'deepxpalm[{extra}]') "
            "or choose backend='numpy'"
        )
    weights, meta = read_weights(path)
    fn, one, classify = BACKEND_TABLE[backend].load(weights, meta, path, num_threads)
    log.info("loaded tilt classifier %s with backend %s", path, backend)
    return TiltClassifier(fn, backend, meta, path, logits_one=one, classify_one=classify)


Weights = dict[str, np.ndarray]
Meta = dict[str, Any]
#: A loaded forward pass: (batch logits, batch-1 logits or None, batch-1 classify or None).
Loaded = tuple[Callable[..., Any], Callable[..., Any] | None, Callable[..., Any] | None]


@dataclass(frozen=True)
class Backend:
    """One way to run the weights: the package it needs, a file it needs, how it loads."""

    module: str  # the Python package that must be installed
    load: Callable[[Weights, Meta, Path, int], Loaded]
    beside_weights: str = ""  # a suffix of a file it needs next to the .npz (".onnx")


def _load_numba(weights: Weights, meta: Meta, path: Path, num_threads: int) -> Loaded:
    try:
        from robot_side.perception.numba_forward import NumbaForward

        fn = NumbaForward(weights, meta)
    except ModelLoadError:
        raise
    except Exception as e:  # numba's own errors: a broken install or toolchain
        raise ModelLoadError(f"the numba backend failed to compile: {e}") from e
    return fn, fn.one, fn.classify_one


def _load_numpy(weights: Weights, meta: Meta, path: Path, num_threads: int) -> Loaded:
    return NumpyForward(weights, meta), None, None


def _load_onnxruntime(weights: Weights, meta: Meta, path: Path, num_threads: int) -> Loaded:
    fn, one = _onnx_logits(path.with_suffix(".onnx"), num_threads)
    return fn, one, None


def _load_torchscript(weights: Weights, meta: Meta, path: Path, num_threads: int) -> Loaded:
    return _torch_logits(weights, meta, scripted=True, num_threads=num_threads), None, None


def _load_torch(weights: Weights, meta: Meta, path: Path, num_threads: int) -> Loaded:
    return _torch_logits(weights, meta, scripted=False, num_threads=num_threads), None, None


#: Every backend by name; a new one is a loader and a line here.
BACKEND_TABLE: dict[str, Backend] = {
    "numba": Backend("numba", _load_numba),
    "numpy": Backend("numpy", _load_numpy),
    "onnxruntime": Backend("onnxruntime", _load_onnxruntime, beside_weights=".onnx"),
    "torchscript": Backend("torch", _load_torchscript),
    "torch": Backend("torch", _load_torch),
}
BACKENDS = tuple(BACKEND_TABLE)


def backend_installed(backend: str) -> bool:
    """Whether the backend's package imports here (the bench picks its default by this)."""
    return importlib.util.find_spec(BACKEND_TABLE[backend].module) is not None


def _usable(backend: str, path: Path) -> bool:
    needs = BACKEND_TABLE[backend].beside_weights
    if needs and not path.with_suffix(needs).is_file():
        return False
    return backend_installed(backend)


def _as_batch(frames: np.ndarray) -> np.ndarray:
    x = np.ascontiguousarray(frames, dtype=np.float32)
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[1:] != FRAME_SHAPE:
        raise ValueError(f"frames must have shape (N, 2, 10, 10), not {np.shape(frames)}")
    return x


def _softmax(z: np.ndarray) -> np.ndarray:
    e = np.exp(z - z.max(axis=1, keepdims=True))
    return (e / e.sum(axis=1, keepdims=True)).astype(np.float32, copy=False)


# --- ONNX Runtime -------------------------------------------------------


def _onnx_logits(
    path: Path, num_threads: int
) -> tuple[Callable[[np.ndarray], Logits], Callable[[np.ndarray], Logits]]:
    """A batch function, and a batch-1 one bound to preallocated input and output buffers."""
    if not path.is_file():
        raise ModelLoadError(
            f"no ONNX graph at {path}: `deepxpalm train` writes it beside the weights; "
            "or use backend='numpy', which needs only the .npz"
        )
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = num_threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    try:
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own untyped errors
        raise ModelLoadError(f"ONNX Runtime cannot load {path}: {e}") from None
    run = session.run
    outputs = ["angle_logits", "position_logits"]

    def logits(x: np.ndarray) -> Logits:
        a, p = run(outputs, {"frames": x})
        return a, p

    # Batch 1 through an IOBinding: no per-call input checks or output
    # allocation, about 170 us less per frame on a cold core (docs/benchmarks.md).
    x1 = np.zeros((1, *FRAME_SHAPE), np.float32)
    a1 = np.zeros((1, N_ANGLES), np.float32)
    p1 = np.zeros((1, N_POSITIONS), np.float32)
    binding = session.io_binding()
    binding.bind_input("frames", "cpu", 0, np.float32, list(x1.shape), x1.ctypes.data)
    for name, buf in zip(outputs, (a1, p1), strict=True):
        binding.bind_output(name, "cpu", 0, np.float32, list(buf.shape), buf.ctypes.data)
    run_bound = session.run_with_iobinding

    def logits_one(frame: np.ndarray) -> Logits:
        x1[0] = frame
        run_bound(binding)
        return a1[0], p1[0]

    return logits, logits_one


# --- torch --------------------------------------------------------------


def _torch_logits(
    weights: dict[str, np.ndarray], meta: dict[str, Any], *, scripted: bool, num_threads: int
) -> Callable[[np.ndarray], Logits]:
    import torch

    from robot_side.perception.model import build_from_weights

    if num_threads > 0 and torch.get_num_threads() != num_threads:
        torch.set_num_threads(num_threads)
    model = build_from_weights(weights, meta)
    if scripted:
        # torch 2.9+ calls TorchScript deprecated in favour of torch.compile, which
        # needs a compiler toolchain on the robot PC; it still works and is faster.
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            traced = torch.jit.trace(model, torch.zeros(1, 2, 10, 10))
            model = torch.jit.freeze(traced)

    def logits(x: np.ndarray) -> Logits:
        with torch.inference_mode():
            a, p = model(torch.from_numpy(x))
        return a.numpy(), p.numpy()

    return logits
