"""The data a fit works on: FitData, the study's runs laid out for the search kernel and the replay.

    FitData.from_runs(runs) / from_buckets(buckets) / from_parquet(path)   the runs, their metadata, the
        kernel's length buckets (SearchBatch parts), the objective, and the scorer over them

Runs are cut into parts of at most `runs_per_part` runs of one padded length (the kernel's layout);
the slim batches and features the relaxed fit differentiates through are kept, or streamed again from
a Parquet study when needed.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from jsve.core._batch import LogBatch, bucket_by_length, iter_chunks
from jsve.core._objective import ObjectiveConfig
from jsve.core._replay import batch_features
from jsve.core._sve import FrameFeatures
from jsve.fitting._kernel import SearchBatch, prepare
from jsve.fitting._scorer import Meter, ReplayScorer
from jsve.io._batching import Bucket, from_runs
from jsve.io._schema import RunLog
from jsve.io._stream import ParquetStudy, iter_buckets, open_study


@dataclass
class FitData:
    """Logs prepared once for fitting: batches, features and the search kernel's layout.

    Attributes:
        batches: LogBatch per part of runs (keypoint bins dropped: the features hold what rules need),
            or empty where they were not kept (`from_parquet`): `iter_slim` and `slim` stream them again.
        features: FrameFeatures per part (empty with `batches`).
        parts: SearchBatch per part (jsve.fitting._kernel.prepare): what the search, Nelder-Mead and
            every per-run score read.
        run_counts: real runs per part (parts may end in padding runs).
        meta: one row per real run, in part order (the order of every [R] array of this module).
        config: how runs are scored.
        buckets: the full buckets (with keypoint bins) the data came from, for
            jsve.evaluation._evaluate; their runs, concatenated, are the runs of `meta`. Empty for
            data streamed from Parquet (`from_parquet`), whose buckets `full_buckets` streams again.
        source: the Parquet study the data was streamed from, or None.
        content_digest: sha256 (hex) of every leaf of the full chunks as they streamed, or None
            (jsve.fitting._stages.data_fingerprint hashes `buckets` then).
        runs_per_part: the most runs of a part (how the buckets were cut into parts).
        searcher: where the fit's searches run: None in this process, else a callable (space, values,
            runs, progress=, desc=) -> SearchResult (jsve.fitting._distributed.ShardedSearch: Dask
            workers). Not part of the data: results are the same either way.
    """

    batches: list[LogBatch]
    features: list[FrameFeatures]
    parts: list[SearchBatch]
    run_counts: list[int]
    meta: pd.DataFrame
    config: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    buckets: list[Bucket] = field(default_factory=list)
    source: ParquetStudy | None = None
    content_digest: str | None = None
    runs_per_part: int = 4096
    searcher: Callable | None = None
    meter: Meter = field(default_factory=Meter)

    @property
    def n_runs(self) -> int:
        return int(sum(self.run_counts))

    @property
    def scorer(self) -> ReplayScorer:
        """The replay of these runs by the search kernel, under `config`, on `searcher`'s workers for
        large requests; every optimiser scores through it (jsve.fitting._scorer)."""
        return ReplayScorer(self.parts, self.run_counts, self.config, self.searcher, meter=self.meter)

    @property
    def n_frames(self) -> int:
        """Valid frames over all runs."""
        pairs = zip(self.parts, self.run_counts, strict=True)
        return int(sum(np.sum(np.asarray(p.valid)[:, :n]) for p, n in pairs))

    def iter_slim(self) -> Iterator[tuple[LogBatch, FrameFeatures, int]]:
        """(slim batch, its features, its real runs) per part in part order: those held, or the Parquet
        study streamed again and cut as it was (about the loading's time) where they were not kept,
        one part in memory at a time."""
        if self.batches:
            yield from zip(self.batches, self.features, self.run_counts, strict=True)
            return
        if self.source is None:
            raise ValueError("FitData holds neither slim batches nor a Parquet study to stream them from")
        chunks = _slim_chunks(iter_buckets(self.source, dtype=self.parts[0].t.dtype), self.runs_per_part)
        for slim, feats, real, _ in chunks:
            yield slim, feats, real

    def slim(self) -> tuple[list[LogBatch], list[FrameFeatures]]:
        """Every part's slim batch and features at once (the relaxed fit differentiates through all of
        them): those held, else streamed again and held from then on (about the search layout's size
        again)."""
        if not self.batches:
            held = list(self.iter_slim())
            self.batches, self.features = [b for b, _, _ in held], [f for _, f, _ in held]
        return self.batches, self.features

    @classmethod
    def from_buckets(
        cls, groups: Sequence[Bucket], config: ObjectiveConfig | None = None, *, runs_per_part: int = 4096
    ) -> FitData:
        """FitData of length buckets (jsve.io._batching.buckets); buckets with more than `runs_per_part` runs
        are cut into parts of that many runs (the last padded)."""
        data = cls._from_chunks(groups, config, runs_per_part=runs_per_part)
        data.buckets = list(groups)
        return data

    @classmethod
    def from_parquet(
        cls,
        path,
        config: ObjectiveConfig | None = None,
        *,
        dtype=jnp.float32,
        runs_per_part: int = 4096,
        keep_slim: bool = False,
    ) -> FitData:
        """FitData of a Parquet study, streamed chunk by chunk (jsve.io._stream.iter_buckets): only the
        search's layout of each part stays in memory, never the keypoint bins or a parsed run;
        `full_buckets` streams the file again where whole runs are needed, `iter_slim` where slim batches
        are (keep_slim: hold those too, at about the search layout's size again)."""
        study = open_study(path)
        if study.n_runs == 0:
            raise ValueError("FitData.from_parquet: no runs")
        missing = [e["source"] for e in study.entries if not e["has_ground_truth"]]
        if missing:
            raise ValueError(
                f"FitData.from_parquet: {len(missing)} runs have no ground truth (first: {missing[0]})"
            )
        digest = hashlib.sha256()

        def hashed(chunks, hasher):
            # sha256 releases the GIL: a chunk is hashed on a thread of its own while the next one is
            # read and its features computed, so hashing costs the loading no time. One chunk at a
            # time, in order.
            pending = None
            for bucket in chunks:
                if pending is not None:
                    pending.result()
                pending = hasher.submit(_hash_leaves, digest, jax.tree_util.tree_leaves(bucket.batch))
                yield bucket
            if pending is not None:
                pending.result()

        with ThreadPoolExecutor(1, thread_name_prefix="jsve-digest") as hasher:
            data = cls._from_chunks(
                hashed(iter_buckets(study, dtype=dtype), hasher), config, runs_per_part=runs_per_part,
                keep_slim=keep_slim,
            )  # fmt: skip
        data.source, data.content_digest = study, digest.hexdigest()
        return data

    @classmethod
    def _from_chunks(cls, groups, config, *, runs_per_part: int, keep_slim: bool = True) -> FitData:
        """Search layouts of buckets (in memory or streamed), and their slim batches and features where
        keep_slim."""
        batches, features, parts, counts, metas = [], [], [], [], []
        # Without a switch model given, the IMU's columns are kept for either.
        imu = config is None or config.switch_model == "imu-coast"
        for slim, feats, real, meta in _slim_chunks(groups, runs_per_part):
            if keep_slim:
                batches.append(slim)
                features.append(feats)
            parts.append(prepare(slim, feats, imu=imu))
            counts.append(real)
            metas.append(meta)
        meta = pd.concat(metas, ignore_index=True)
        return cls(
            batches, features, parts, counts, meta, config or ObjectiveConfig(), runs_per_part=runs_per_part
        )

    def meta_order(self, run_ids) -> np.ndarray:
        """Position in `meta` of each run id (for putting per-run results in `meta`'s order)."""
        position = pd.Series(np.arange(len(self.meta)), index=self.meta["run_id"].to_numpy())
        return position.loc[np.asarray(run_ids)].to_numpy()

    def full_buckets(self, *, by_length: bool = False) -> Iterable[Bucket]:
        """The runs with everything (keypoint bins included) for jsve.evaluation.evaluate, in the order
        of `meta`: the buckets held, or the Parquet study streamed again.

        by_length: shortest padded length first instead, every chunk of a length together (iter_buckets'
        by_length), so that a pass can drop what it compiled for a length once past it; put results
        back in `meta`'s order with jsve.evaluation.in_run_order and `meta_order`.
        """
        if self.source is None:
            if by_length:
                return sorted(self.buckets, key=lambda b: b.batch.n_frames)
            return self.buckets
        return iter_buckets(self.source, dtype=self.parts[0].t.dtype, by_length=by_length)

    @classmethod
    def from_runs(
        cls,
        runs: Sequence[RunLog],
        config: ObjectiveConfig | None = None,
        *,
        dtype=jnp.float32,
        max_padding: float = 0.1,
    ) -> FitData:
        """FitData of parsed runs (bucketed by length, float32 by default)."""
        if not runs:
            raise ValueError("FitData.from_runs: no runs")
        missing = [r.source for r in runs if not r.has_ground_truth]
        if missing:
            raise ValueError(
                f"FitData.from_runs: {len(missing)} runs have no ground truth (first: {missing[0]})"
            )
        # jsve.core._batch groups by padding; groups that pad to the same length (e.g. equal-length runs) are
        # merged here, since for fitting every extra shape is another compilation.
        lengths = [len(r.frames) for r in runs]
        groups: list[list[int]] = []
        for group in bucket_by_length(lengths, max_padding=max_padding):
            padded = _padded(max(lengths[i] for i in group))
            if groups and _padded(max(lengths[i] for i in groups[-1])) == padded:
                groups[-1].extend(int(i) for i in group)
            else:
                groups.append([int(i) for i in group])
        return cls.from_buckets([from_runs([runs[i] for i in g], dtype=dtype) for g in groups], config)

    def split_weights(self, weights) -> list[jax.Array]:
        """Per-part weight arrays (padding runs 0) of [R] run weights."""
        w = np.asarray(weights, np.float64)
        if w.shape != (self.n_runs,):
            raise ValueError(f"weights must have shape ({self.n_runs},) (one per run), got {w.shape}")
        out, start = [], 0
        for part, n in zip(self.parts, self.run_counts, strict=True):
            chunk = np.zeros(part.n_runs)
            chunk[:n] = w[start : start + n]
            out.append(jnp.asarray(chunk, part.t.dtype))
            start += n
        return out


def _hash_leaves(digest, leaves) -> None:
    """Add arrays to a hashlib digest: each one's dtype and shape, then its bytes."""
    for leaf in leaves:
        array = np.ascontiguousarray(leaf)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.reshape(-1).view(np.uint8).data)


def _slim_chunks(groups: Iterable[Bucket], runs_per_part: int):
    """(slim batch, features, real runs, their meta rows) per part of buckets: a bucket cut into parts
    of at most runs_per_part runs (its meta may hold fewer runs than its batch, whose last runs are then
    padding; a part of padding alone is skipped), the keypoint bins dropped once the features hold
    what rules need of them."""
    for bucket in groups:
        n_real = len(bucket.meta)
        size = min(bucket.batch.n_runs, runs_per_part)
        for runs, chunk in iter_chunks(bucket.batch, size):
            real = max(0, min(runs.stop, n_real) - runs.start)
            if real == 0:
                continue
            chunk = jax.tree.map(jnp.asarray, chunk)
            feats = batch_features(chunk)
            slim = eqx.tree_at(lambda b: b.bins, chunk, jnp.zeros((chunk.n_runs, 1, 64), chunk.bins.dtype))
            yield slim, feats, real, bucket.meta.iloc[runs.start : runs.start + real]


def _padded(n: int, multiple: int = 64) -> int:
    """jsve.core._batch's padded length of a run of n frames."""
    return max(multiple, -(-n // multiple) * multiple)


def _default_weights(data: FitData, weights) -> np.ndarray:
    w = np.ones(data.n_runs) if weights is None else np.asarray(weights, np.float64)
    if w.shape != (data.n_runs,) or np.any(w < 0) or not np.any(w > 0):
        raise ValueError(f"weights must be {data.n_runs} non-negative numbers, not all 0")
    return w


__all__ = ["FitData"]
