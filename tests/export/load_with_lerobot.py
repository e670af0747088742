"""Run in the lerobot-dataset environment: load a dataset, save every item as arrays.

Usage: python load_with_lerobot.py DATASET_ROOT OUT.npz
(or ``load``, from ``lerobot_server.py``: one interpreter for a test module's loads)
"""

import json
import sys
import types

# PyPI's torchvision wheels are built against the CUDA build of torch; with
# the CPU build its compiled operators (nms, ...) do not load and its
# meta-registrations fail at import. LeRobotDataset only uses torchvision's
# Python transforms and video readers, so the registrations are skipped.
sys.modules["torchvision._meta_registrations"] = types.ModuleType("torchvision._meta_registrations")

import numpy as np  # noqa: E402
from ledataset.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402


def load(root: str, out: str) -> None:
    """Every item of the dataset at ``root``, as arrays, and its metadata, into ``out`` (.npz)."""
    ds = LeRobotDataset("deepxpalm/export", root=root)
    columns: dict[str, list] = {}
    tasks = []
    for i in range(len(ds)):
        item = ds[i]
        for key, value in item.items():
            if key == "task":
                tasks.append(value)
                continue
            value = np.asarray(value)
            if key in ds.meta.video_keys:  # 0..1 floats, channels first: stored as 0..255 bytes
                value = np.round(value * 255).astype(np.uint8)
            columns.setdefault(key, []).append(value)
    arrays = {k: np.stack(v) for k, v in columns.items()}
    episodes = ds.meta.episodes
    meta = {
        "fps": ds.fps,
        "num_episodes": ds.num_episodes,
        "num_frames": ds.num_frames,
        "tasks": tasks,
        "episodes": [
            {
                k: episodes[i][k]
                for k in (
                    "episode_index",
                    "length",
                    "dataset_from_index",
                    "dataset_to_index",
                    "deepxpalm/session",
                    "deepxpalm/t_first_ns",
                    *(f"videos/{k}/from_timestamp" for k in ds.meta.video_keys),
                )
            }
            for i in range(len(episodes))
        ],
        "stats_keys": sorted(ds.meta.stats),
        "features": ds.meta.features,
        "video_keys": ds.meta.video_keys,
        "video_backend": ds.video_backend,
    }
    np.savez(out, **arrays, _meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))


if __name__ == "__main__":
    load(sys.argv[1], sys.argv[2])
