"""LeRobot's dataset format, version 3.0, written with pyarrow alone.

Layout (what LeRobot's ``LeRobotDataset`` reads)::

    meta/info.json                      fps, features, counts, path templates
    meta/stats.json                     min, max, mean, std, count per feature
    meta/tasks.parquet                  task string (index) -> task_index
    meta/episodes/chunk-000/file-000.parquet   one row per episode: where its
                                        rows are, its length, its own stats
    data/chunk-000/file-000.parquet     one row per frame, every feature

Rows are written as they come, in record batches of ``batch_rows``; a data
file is closed at an episode boundary once it passes ``file_size_mb`` (an
episode's rows stay in one file, as the format requires). Statistics are
running sums, so memory does not grow with the recording. Quantiles
(LeRobot's optional q01..q99) are not written: they need every value.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from deploy.export.schema import DEFAULT_FEATURES, Feature
from deploy.export.video import VIDEO_PATH, VideoFeatureWriter

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # files per chunk folder
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
ROBOT_TYPE = "ur3e_robotiq2f_tactile"


class RunningStats:
    """Element-wise min, max, mean and std of a feature over rows, in float64."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.n = 0
        self.sum = np.zeros(shape)
        self.sumsq = np.zeros(shape)
        self.min = np.full(shape, np.inf)
        self.max = np.full(shape, -np.inf)

    def update(self, values: np.ndarray) -> None:
        v = values.astype(np.float64, copy=False)
        self.n += len(v)
        self.sum += v.sum(axis=0)
        self.sumsq += np.square(v).sum(axis=0)
        np.minimum(self.min, v.min(axis=0), out=self.min)
        np.maximum(self.max, v.max(axis=0), out=self.max)

    def merge(self, other: RunningStats) -> None:
        self.n += other.n
        self.sum += other.sum
        self.sumsq += other.sumsq
        np.minimum(self.min, other.min, out=self.min)
        np.maximum(self.max, other.max, out=self.max)

    def as_dict(self) -> dict[str, list]:
        n = max(self.n, 1)
        mean = self.sum / n
        std = np.sqrt(np.maximum(self.sumsq / n - mean**2, 0.0))
        return {
            "min": self.min.tolist(),
            "max": self.max.tolist(),
            "mean": mean.tolist(),
            "std": std.tolist(),
            "count": [self.n],
        }


def _arrow_column(values: np.ndarray, shape: tuple[int, ...]) -> pa.Array:
    """(rows, *shape) -> a primitive column for shape (1,), else nested fixed-size lists."""
    if shape == (1,):
        return pa.array(values.reshape(-1))
    arr: pa.Array = pa.array(values.reshape(-1))
    for size in reversed(shape):
        arr = pa.FixedSizeListArray.from_arrays(arr, size)
    return arr


class LeRobotV3Writer:
    """Streams rows into a LeRobot v3.0 dataset folder."""

    def __init__(
        self,
        root: Path,
        features: list[Feature],
        fps: int,
        *,
        batch_rows: int = 1024,
        file_size_mb: float = 100.0,
        video_codec: str = "libx264",
    ) -> None:
        self.root = Path(root)
        self.features = features
        self.fps = fps
        self.batch_rows = batch_rows
        self.file_size_bytes = file_size_mb * 1e6
        self.columns: dict[str, tuple[str, tuple[int, ...]]] = {
            f.name: (f.dtype, f.shape) for f in features if f.dtype != "video"
        }
        #: each camera's MP4 writer: its pictures are not parquet columns
        self.videos = {
            f.name: VideoFeatureWriter(root, f.name, f.shape[1], f.shape[0], fps, video_codec)
            for f in features
            if f.dtype == "video"
        }
        for name, ft in DEFAULT_FEATURES.items():
            self.columns[name] = (ft["dtype"], tuple(ft["shape"]))
        self.buffers = {
            name: np.empty((batch_rows, *shape), dtype=dtype)
            for name, (dtype, shape) in self.columns.items()
        }
        self.schema = pa.schema(
            [
                (name, _arrow_column(np.zeros((0, *shape), dtype), shape).type)
                for name, (dtype, shape) in self.columns.items()
            ]
        )
        self.fill = 0
        self.index = 0  # global row index
        self.tasks: dict[str, int] = {}
        self.episodes: list[dict[str, Any]] = []
        self.stats = {name: RunningStats(shape) for name, (_, shape) in self.columns.items()}
        self.ep_stats: dict[str, RunningStats] | None = None
        self.ep: dict[str, Any] | None = None
        self.file_index = 0
        self.writer: pq.ParquetWriter | None = None

    # ---------------------------------------------------------------- rows
    def begin_episode(self, task: str, extra: dict[str, Any]) -> None:
        task_index = self.tasks.setdefault(task, len(self.tasks))
        if self.writer is None:
            path = self.root / DATA_PATH.format(
                chunk_index=self.file_index // CHUNKS_SIZE, file_index=self.file_index % CHUNKS_SIZE
            )
            path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(path, self.schema, compression="zstd")
            self._path = path
        self.ep = {
            "episode_index": len(self.episodes),
            "tasks": [task],
            "task_index": task_index,
            "dataset_from_index": self.index,
            "data/chunk_index": self.file_index // CHUNKS_SIZE,
            "data/file_index": self.file_index % CHUNKS_SIZE,
            **extra,
        }
        self.ep_stats = {name: RunningStats(shape) for name, (_, shape) in self.columns.items()}
        for name, video in self.videos.items():
            self.ep.update(video.begin_episode())
            self.ep_stats[name] = RunningStats((3,))
        self.frame_index = 0

    def add(self, row: dict[str, Any]) -> None:
        i = self.fill
        b = self.buffers
        for name in self.columns:
            if name in row:
                b[name][i] = row[name]
        b["timestamp"][i] = self.frame_index / self.fps
        b["frame_index"][i] = self.frame_index
        b["episode_index"][i] = self.ep["episode_index"]
        b["index"][i] = self.index
        b["task_index"][i] = self.ep["task_index"]
        for name, video in self.videos.items():
            self.ep_stats[name].update(video.add(row[name]))
        self.fill += 1
        self.frame_index += 1
        self.index += 1
        if self.fill == self.batch_rows:
            self._flush()

    def end_episode(self) -> None:
        self._flush()
        ep = self.ep
        for video in self.videos.values():
            ep.update(video.end_episode())
        ep["dataset_to_index"] = self.index
        ep["length"] = self.index - ep["dataset_from_index"]
        for name, st in self.ep_stats.items():
            for stat, value in _stats_dict(name, st, self.videos).items():
                ep[f"stats/{name}/{stat}"] = value
            self.stats.setdefault(name, RunningStats(st.sum.shape)).merge(st)
        del ep["task_index"]
        self.episodes.append(ep)
        self.ep = self.ep_stats = None
        if self._path.stat().st_size > self.file_size_bytes:  # the next episode: a new file
            self.writer.close()
            self.writer = None
            self.file_index += 1

    def _flush(self) -> None:
        n = self.fill
        if n == 0:
            return
        arrays = []
        for name, (_, shape) in self.columns.items():
            values = self.buffers[name][:n]
            self.ep_stats[name].update(values.reshape(n, *shape))
            arrays.append(_arrow_column(values, shape))
        self.writer.write_batch(pa.record_batch(arrays, schema=self.schema))
        self.fill = 0

    # ---------------------------------------------------------------- meta
    def finish(self, provenance: dict[str, Any]) -> dict[str, Any]:
        """Close the data file and write meta/; returns info.json's content."""
        if self.ep is not None:
            self.end_episode()
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        for video in self.videos.values():
            video.finish()
        meta = self.root / "meta"
        meta.mkdir(parents=True, exist_ok=True)
        features = {f.name: f.info() for f in self.features}
        for name, video in self.videos.items():
            features[name]["info"] = video.info()
        features.update(DEFAULT_FEATURES)
        total = self.index
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": ROBOT_TYPE,
            "total_episodes": len(self.episodes),
            "total_frames": total,
            "total_tasks": len(self.tasks),
            "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": round(self.file_size_bytes / 1e6),
            "video_files_size_in_mb": 200,
            "fps": self.fps,
            "splits": {"train": f"0:{len(self.episodes)}"},
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.videos else None,
            "features": features,
        }
        _write_json(meta / "info.json", info)
        stats = {k: _stats_dict(k, s, self.videos) for k, s in self.stats.items() if s.n}
        _write_json(meta / "stats.json", stats)
        self._write_tasks(meta / "tasks.parquet")
        self._write_episodes()
        _write_json(meta / "deepxpalm.json", provenance)
        return info

    def _write_tasks(self, path: Path) -> None:
        """The task strings as the pandas index LeRobot looks tasks up in."""
        names = sorted(self.tasks, key=self.tasks.get)
        table = pa.table({"task_index": pa.array([self.tasks[t] for t in names], pa.int64())})
        table = table.append_column("task", pa.array(names, pa.string()))
        pandas_meta = {
            "index_columns": ["task"],
            "column_indexes": [],
            "columns": [
                {
                    "name": "task_index",
                    "field_name": "task_index",
                    "pandas_type": "int64",
                    "numpy_type": "int64",
                    "metadata": None,
                },
                {
                    "name": "task",
                    "field_name": "task",
                    "pandas_type": "unicode",
                    "numpy_type": "object",
                    "metadata": None,
                },
            ],
            "creator": {"library": "pyarrow", "version": pa.__version__},
            "pandas_version": "2.0.0",
        }
        table = table.replace_schema_metadata({"pandas": json.dumps(pandas_meta)})
        pq.write_table(table, path)

    def _write_episodes(self) -> None:
        for ep in self.episodes:
            ep["meta/episodes/chunk_index"] = 0
            ep["meta/episodes/file_index"] = 0
        path = self.root / EPISODES_PATH
        path.parent.mkdir(parents=True, exist_ok=True)
        columns = (
            {k: [ep[k] for ep in self.episodes] for k in self.episodes[0]} if self.episodes else {}
        )
        pq.write_table(
            pa.table(columns) if columns else pa.table({"episode_index": pa.array([], pa.int64())}),
            path,
        )


def _stats_dict(name: str, st: RunningStats, videos: dict) -> dict[str, list]:
    """A camera's per-channel stats in LeRobot's image shape (3, 1, 1); others as they are."""
    out = st.as_dict()
    if name in videos:
        out = {k: v if k == "count" else [[[x]] for x in v] for k, v in out.items()}
    return out


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2, allow_nan=False, default=_json_default) + "\n")


def _json_default(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return str(value)
