"""Import the heavy third-party packages and compile the project once, so their bytecode is
written once.

``make setup`` installs with ``--no-compile`` (compiling every file of every
package took 31 of the install's 58 s), so Python compiles a module the first
time something imports it and keeps the result. On a fresh clone the test
lanes' first processes (four workers, then the nodes, simulators and browsers
they start) would all compile torch, SciPy, aiortc, MuJoCo ... at the same
moment: about 5 s more CPU each than with the bytecode there. One process
before the lanes compiles only what is imported, once. A package that is
not installed (or that cannot load) is skipped, so this runs on any role's
install.
"""

from __future__ import annotations

import compileall
import importlib
import time
import tomllib
from pathlib import Path

#: what the suite's processes import between them, heaviest first: the packages, and the
#: submodules they load only when asked (a fresh clone's fast lane compiled 1,742 modules,
#: torch._dynamo with SymPy, pandas with pingouin, pytest and hypothesis in each worker at once)
PACKAGES = (
    "torch",
    "torch._dynamo",  # an optimizer's first step; SymPy with it
    "pingouin",  # the study's statistics: pandas, xarray, seaborn, statsmodels
    "scipy.signal",
    "matplotlib.pyplot",
    "mujoco",
    "OpenGL.GL",  # the lab's camera
    "OpenGL.EGL",
    "aiortc",
    "av",
    "numba",
    "onnx",
    "torch.onnx",  # training writes its graph
    "onnxruntime",
    "pyarrow.parquet",
    "foxglove",
    "foxglove_schemas_protobuf",
    "mcap.reader",
    "jsonschema",
    "nacl.signing",
    "cryptography.x509",  # the fabric's certificates
    "websockets.sync.client",
    "zmq",
    "msgpack",
    "scservo_sdk",
    "PIL.Image",
    "pytest",
    "xdist",
    "execnet",
    "hypothesis.extra.numpy",
)

ROOT = Path(__file__).resolve().parent.parent


def project_packages() -> list[str]:
    """The project's own packages, as pyproject.toml has setuptools find them."""
    found = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return [pattern.rstrip("*") for pattern in found["packages"]["find"]["include"]]


def main() -> None:
    t0 = time.monotonic()
    done = []
    for name in PACKAGES:
        try:
            importlib.import_module(name)
        except Exception:  # not installed, or no library under it (OpenGL without a GL): skipped
            continue
        done.append(name)
    for package in project_packages():  # compiled whole: they are small
        compileall.compile_dir(ROOT / package, quiet=1)
    took = time.monotonic() - t0
    print(f"bytecode written for {', '.join(done)} and this project ({took:.1f} s)")


if __name__ == "__main__":
    main()
