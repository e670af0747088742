"""Print the uv arguments that install from where pip is configured to install from.

``make setup`` installs the project's dependencies with uv (torch stays pip's:
README.md). uv does not read pip's configuration, so a machine whose pip takes
its packages from a local mirror, a wheel folder or a constraints file (pip.conf,
``PIP_*`` variables) would have uv go elsewhere. This reads ``pip config list``
and prints the same sources as uv options, one shell word per line:

    index-url        -> --default-index
    extra-index-url  -> --extra-index-url (each)
    find-links       -> --find-links (each)
    constraint       -> --constraint (each)
    no-index         -> --no-index

With several indexes, uv takes the best version across all of them, as pip
does (``--index-strategy unsafe-best-match``). Nothing configured: nothing
printed, and uv uses PyPI as pip would.

    .venv/bin/python scripts/pip-config-as-uv-args.py
"""

from __future__ import annotations

import re
import subprocess
import sys

#: pip option -> uv option; a list option's value is split on white space
OPTIONS = {
    "index-url": "--default-index",
    "extra-index-url": "--extra-index-url",
    "find-links": "--find-links",
    "constraint": "--constraint",
}
LINE = re.compile(r"^[^.]*\.(?P<key>[a-z-]+)='(?P<value>.*)'$")


def uv_args(pip_config: str) -> list[str]:
    """uv options for ``pip config list``'s output (later lines win for a single value)."""
    single: dict[str, str] = {}
    many: dict[str, list[str]] = {}
    no_index = False
    for line in pip_config.splitlines():
        m = LINE.match(line.strip())
        if m is None:
            continue
        key, value = m["key"], m["value"]
        if key == "no-index":
            no_index = value.lower() in ("1", "true", "yes", "on")
        elif key == "index-url":
            single[key] = value
        elif key in OPTIONS:
            for word in value.split():
                if word not in many.setdefault(key, []):
                    many[key].append(word)
    args: list[str] = []
    if "index-url" in single:
        args += [OPTIONS["index-url"], single["index-url"]]
    for key, words in many.items():
        for word in words:
            args += [OPTIONS[key], word]
    if no_index:
        args.append("--no-index")
    if "extra-index-url" in many or "find-links" in many:
        args += ["--index-strategy", "unsafe-best-match"]
    return args


def main() -> int:
    out = subprocess.run(
        [sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True
    )
    print("\n".join(uv_args(out.stdout if out.returncode == 0 else "")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
