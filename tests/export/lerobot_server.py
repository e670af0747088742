"""Run in the LeRobot environment: answers a test module's loads from one interpreter.

Usage: python lerobot_server.py  (requests on stdin, answers on stdout, one JSON object a line)

Importing LeRobot (torch, torchvision, datasets, pandas) costs about 12 s of
CPU, far more than loading a small dataset; a module that loads three pays
it once here. Requests:

    {"op": "load", "root": DATASET_ROOT, "out": OUT_NPZ}   -> {"ok": true}
    {"op": "policy", "root": DATASET_ROOT}                 -> {"ok": true, "result": {...}}

A request that fails answers ``{"ok": false, "error": TRACEBACK}`` and the
server goes on with the next one. Whatever the libraries print goes to
stderr, so stdout holds only the answers.
"""

import json
import os
import sys
import traceback

answers = os.fdopen(os.dup(1), "w")
os.dup2(2, 1)


def answer(request: dict) -> dict:
    if request["op"] == "load":
        import load_with_lerobot

        load_with_lerobot.load(request["root"], request["out"])
        return {"ok": True}
    if request["op"] == "policy":
        import policy_features

        return {"ok": True, "result": policy_features.report(request["root"])}
    raise ValueError(f"unknown request {request['op']!r}")


for line in sys.stdin:
    try:
        reply = answer(json.loads(line))
    except Exception:
        reply = {"ok": False, "error": traceback.format_exc()}
    answers.write(json.dumps(reply) + "\n")
    answers.flush()
