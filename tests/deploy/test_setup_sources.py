"""uv installs from the sources pip is configured with (scripts/pip-config-as-uv-args.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "pip-config-as-uv-args.py"


def _uv_args(pip_config: str) -> list[str]:
    spec = importlib.util.spec_from_file_location("pip_config_as_uv_args", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.uv_args(pip_config)


def test_a_mirror_a_wheel_folder_and_constraints_become_uv_options():
    config = "\n".join(
        [
            ":env:.find-links='/opt/wheels'",
            "global.constraint='/etc/xdg/pip/constraints.txt'",
            "global.extra-index-url='file:///opt/a/simple file:///opt/b/simple'",
            "global.find-links='/opt/wheels'",  # the same folder twice: named once
            "global.cert='/etc/ssl/certs/ca-certificates.crt'",  # not a source: left out
        ]
    )
    args = _uv_args(config)
    assert args == [
        *("--find-links", "/opt/wheels"),
        *("--constraint", "/etc/xdg/pip/constraints.txt"),
        *("--extra-index-url", "file:///opt/a/simple"),
        *("--extra-index-url", "file:///opt/b/simple"),
        *("--index-strategy", "unsafe-best-match"),  # pip's choice across indexes
    ]


def test_an_index_replacing_pypi_and_no_index():
    assert _uv_args("global.index-url='https://mirror.example/simple'") == [
        *("--default-index", "https://mirror.example/simple"),
    ]
    assert _uv_args("global.no-index='true'") == ["--no-index"]
    assert _uv_args("") == []  # nothing configured: PyPI, as pip
