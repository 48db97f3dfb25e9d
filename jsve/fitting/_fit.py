"""Fit a switching rule's weights and thresholds to minimise position error over many logs.

Three stages, all on the same replay (docs/fitting.md):

1. Batched search (jsve.fitting._search): a quasi-random design of thousands of settings (Sobol by default,
   the seed's presets added) evaluated on every run at once; the per-run loss matrix is kept, so that
   cross-validation folds and bootstrap resamples reweight it instead of replaying again.
2. Nelder-Mead on the exact (hard) objective (jsve's own driver, jsve.fitting._simplex, moving many
   simplexes in lockstep), started from the best searched points, in the unconstrained coordinates of
   jsve.fitting._space (so every iterate is a valid rule).
3. Optionally, optimistix BFGS on the relaxed objective (SoftLogic with a temperature, annealed towards
   0; jsve.core._objective), whose result is kept only when the hard objective agrees it is better.

    data = FitData.from_runs(runs)
    result = fit(data, sve_space(), group_weights(data.meta))
    result.rule            # an SVERule; jsve.core._rules.rule_to_dict(result.rule) for JSON
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from jsve._memory import release_memory
from jsve.core._batch import LogBatch, bucket_by_length, iter_chunks
from jsve.core._machine import SoftLogic
from jsve.core._objective import ObjectiveConfig, run_losses
from jsve.core._replay import batch_features
from jsve.core._sve import FrameFeatures
from jsve.fitting._designs import design
from jsve.fitting._halving import RunLossCache, halving_search, rung_sizes, stratified_order
from jsve.fitting._polish import polish_in_lockstep
from jsve.fitting._scorer import Meter, ReplayScorer
from jsve.fitting._search import SearchBatch, SearchResult, prepare, search_chunk
from jsve.fitting._space import ParamSpace, preset_values
from jsve.io._batching import Bucket, from_runs
from jsve.io._schema import RunLog
from jsve.io._stream import ParquetStudy, iter_buckets, open_study

log = logging.getLogger(__name__)

DEFAULT_TEMPERATURES = (0.1, 0.03, 0.01, 0.003)
"""Annealing schedule of the relaxed fit, in SVE units (x250 for inlier thresholds). It starts broad:
at a temperature much below the distance of most scores from the thresholds every sigmoid saturates
and the relaxed objective is flat (no gradient) far from the optimum."""


def fitted_rule_name(family: str) -> str:
    """The name of a family's fitted rule in every table, beside the presets' names: "fitted-<family>".

    Arguments:
        family: a rule family ("sve" or "inliers", jsve.core's rule kinds).
    Returns:
        "fitted-sve", "fitted-inliers".
    """
    return f"fitted-{family}"


# ---------------------------------------------------------------------------------------------------
# Data


@dataclass
class FitData:
    """Logs prepared once for fitting: batches, features and the search kernel's layout.

    Attributes:
        batches: LogBatch per part of runs (keypoint bins dropped: the features hold what rules need),
            or empty where they were not kept (`from_parquet`): `iter_slim` and `slim` stream them again.
        features: FrameFeatures per part (empty with `batches`).
        parts: SearchBatch per part (jsve.fitting._search.prepare): what the search, Nelder-Mead and
            every per-run score read.
        run_counts: real runs per part (parts may end in padding runs).
        meta: one row per real run, in part order (the order of every [R] array of this module).
        config: how runs are scored.
        buckets: the full buckets (with keypoint bins) the data came from, for
            jsve.evaluation._evaluate; their runs, concatenated, are the runs of `meta`. Empty for
            data streamed from Parquet (`from_parquet`), whose buckets `full_buckets` streams again.
        source: the Parquet study the data was streamed from, or None.
        content_digest: sha256 (hex) of every leaf of the full chunks as they streamed, or None
            (jsve.fitting._study.data_fingerprint hashes `buckets` then).
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


# ---------------------------------------------------------------------------------------------------
# Objectives of one setting


def _included_mean(parts):
    """sum w x loss / sum w over the included runs of (loss, included, w) per part; over all runs where
    none is included (whose losses are then the penalty), as jsve.core._objective.weighted_objective."""
    num_in = sum(jnp.sum(w * inc * loss) for loss, inc, w in parts)
    den_in = sum(jnp.sum(w * inc) for _, inc, w in parts)
    num_all = sum(jnp.sum(w * loss) for loss, _, w in parts)
    den_all = sum(jnp.sum(w) for _, _, w in parts)
    return jnp.where(den_in > 0, num_in / jnp.where(den_in > 0, den_in, 1.0), num_all / den_all)


def _hard_value(z, parts, weights, space: ParamSpace, config: ObjectiveConfig):
    """Weighted mean hard loss of the setting with unconstrained coordinates z (the search kernel, S = 1)."""
    rule = space.rule(space.values_from_z(z)[None])
    results = [(search_chunk(sb, rule, config), w) for sb, w in zip(parts, weights, strict=True)]
    return _included_mean([(r.loss[0], r.included[0].astype(w.dtype), w) for r, w in results])


def _relaxed_value(z, batches, features, weights, temperature, space: ParamSpace, config: ObjectiveConfig):
    """Weighted mean relaxed loss (SoftLogic(temperature x score scale)); differentiable in z."""
    rule = space.rule(space.values_from_z(z))
    logic = SoftLogic(temperature * space.score_scale)
    losses = [
        (run_losses(b, rule, f, config, logic=logic), w)
        for b, f, w in zip(batches, features, weights, strict=True)
    ]
    return _included_mean([(r.loss, r.included, w) for r, w in losses])


def hard_objective(data: FitData, space: ParamSpace, values, weights=None) -> float:
    """The hard objective (metres) of one setting's free values."""
    w = data.split_weights(_default_weights(data, weights))
    return float(
        _hard_jit(
            space.z_from_values(jnp.asarray(values, data.parts[0].t.dtype)), data.parts, w, space, data.config
        )
    )


def relaxed_objective(data: FitData, space: ParamSpace, values, temperature: float, weights=None) -> float:
    """The relaxed objective (metres) of one setting at a temperature in SVE units."""
    w = data.split_weights(_default_weights(data, weights))
    batches, features = data.slim()
    z = space.z_from_values(jnp.asarray(values, data.parts[0].t.dtype))
    return float(_relaxed_jit(z, batches, features, w, jnp.asarray(temperature, z.dtype), space, data.config))


_hard_jit = eqx.filter_jit(_hard_value)
_relaxed_jit = eqx.filter_jit(_relaxed_value)
_relaxed_grad = eqx.filter_jit(jax.value_and_grad(_relaxed_value))


# ---------------------------------------------------------------------------------------------------
# Optimisers


@eqx.filter_jit
def _bfgs(z0, batches, features, weights, temperature, space, config, max_steps, rtol, atol):
    def fn(z, args):
        return _relaxed_value(z, args[0], args[1], args[2], args[3], space, config)

    solver = optx.BFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(
        fn, solver, z0, args=(batches, features, weights, temperature), max_steps=max_steps, throw=False
    )
    return sol.value, sol.stats["num_steps"]


def nelder_mead(
    data: FitData,
    space: ParamSpace,
    start,
    weights=None,
    *,
    max_steps: int = 200,
    step: float = 0.5,
    rtol: float = 1e-4,
    atol: float = 1e-4,
    window: int = 0,
    ftol: float = 1e-4,
    on_runs: int = 0,
    seed: int = 0,
    pool=None,
) -> tuple[np.ndarray, float, int]:
    """Nelder-Mead on the hard objective from `start` (free values): one run of the fit's polish
    (jsve.fitting._simplex.lockstep_nelder_mead; `polish_fits` moves many together).

    on_runs: where more runs have weight, the simplex moves on the first on_runs of them in the study's
    stratified order (seeded by `seed`), packed by length class (jsve.fitting._polish); 0: on every run.
    pool: [R] the weights those runs are drawn from (a fold: the study's, `polish_runs`); default weights.

    The simplex starts at the start's unconstrained coordinates z plus `step` along each axis (a step
    of 0.5 in z moves a value at mid-box by ~12 % of its box). The hard objective is piecewise constant
    in the thresholds (finitely many frames), which a simplex method handles where gradients cannot.
    window, ftol: stop once `window` steps improve the best value by at most `ftol` metres; window 0:
    run to the simplex's convergence test or max_steps.

    Returns:
        (values [d], hard objective at them over every run with weight, steps taken).
    """
    w = _default_weights(data, weights)
    ended = polish_in_lockstep(
        data, space, [w], [(0, np.asarray(start, np.float64))], n_runs=on_runs, seed=seed, step=step,
        max_steps=max_steps, window=window, ftol=ftol, rtol=rtol, atol=atol, pool=pool,
    )  # fmt: skip
    values = ended.values[0]
    # The objective on every run with weight: where the polish ran on a subset, the verdict is not its.
    z = space.z_from_values(jnp.asarray(values, data.parts[0].t.dtype))
    value = float(_hard_jit(z, data.parts, data.split_weights(w), space, data.config))
    return values, value, int(ended.steps[0])


def relaxed_fit(
    data: FitData,
    space: ParamSpace,
    start,
    weights=None,
    *,
    temperatures: Sequence[float] = DEFAULT_TEMPERATURES,
    max_steps: int = 60,
    rtol: float = 1e-4,
    atol: float = 1e-5,
) -> tuple[np.ndarray, list[dict]]:
    """optimistix BFGS on the relaxed objective, annealing the temperature (SVE units) from high to low.

    Returns:
        (values [d] after the last temperature, one dict per temperature: temperature, relaxed value,
        hard value, steps).
    """
    w = data.split_weights(_default_weights(data, weights))
    batches, features = data.slim()
    dtype = data.parts[0].t.dtype
    z = space.z_from_values(jnp.asarray(start, dtype))
    history = []
    for temperature in temperatures:
        tau = jnp.asarray(temperature, dtype)
        z, steps = _bfgs(
            z,
            batches,
            features,
            w,
            tau,
            space,
            data.config,
            int(max_steps),
            float(rtol),
            float(atol),
        )
        relaxed = float(_relaxed_jit(z, batches, features, w, tau, space, data.config))
        hard = float(_hard_jit(z, data.parts, w, space, data.config))
        history.append(
            {"temperature": float(temperature), "relaxed": relaxed, "hard": hard, "steps": int(steps)}
        )
        log.info(
            "relaxed fit T=%g: relaxed %.5f m, hard %.5f m (%d steps)", temperature, relaxed, hard, steps
        )
    return np.asarray(space.values_from_z(z), np.float64), history


# ---------------------------------------------------------------------------------------------------
# The whole fit


@dataclass(frozen=True)
class FitConfig:
    """How `fit` searches and optimises.

    Attributes:
        design: "sobol", "halton" or "random"; n_search: its number of settings; seed: its seed (and
            the halving's order of runs).
        search: "exhaustive" (every setting on every run), "halving" (successive halving over runs,
            jsve.fitting._halving: all settings on a stratified share `initial_fraction` of the runs,
            the best 1/eta on eta times as many, ..., the last ones on all runs) or "auto" (the
            default: `resolve_search` picks one by the study's size, and halving's initial_fraction).
        include_presets: add the family's presets (and `starts`) to the design.
        n_starts: Nelder-Mead runs, from the best searched settings; nm_steps: their step limit;
            nm_step: initial simplex size in unconstrained coordinates; nm_window, nm_ftol: a run stops
            once nm_window steps improve its best value by at most nm_ftol metres (0: no stall test;
            jsve.fitting._simplex); polish_runs: where more runs
            have weight, Nelder-Mead moves on that many of them (a stratified subset packed into one
            part, jsve.fitting._polish) and its result is judged on all; 0: on every run.
        relaxed: also run the annealed BFGS on the relaxed objective from the best point so far.
        temperatures, bfgs_steps: its schedule (SVE units) and step limit per temperature.
    """

    design: str = "sobol"
    n_search: int = 2048
    seed: int = 0
    search: str = "auto"
    eta: float = 3.0
    initial_fraction: float = 1 / 9
    include_presets: bool = True
    n_starts: int = 2
    nm_steps: int = 200
    nm_step: float = 0.5
    nm_window: int = 25
    nm_ftol: float = 1e-4
    polish_runs: int = 256
    relaxed: bool = False
    temperatures: tuple[float, ...] = DEFAULT_TEMPERATURES
    bfgs_steps: int = 40

    def __post_init__(self):
        if self.search not in SEARCH_METHODS:
            raise ValueError(f"FitConfig.search must be one of {SEARCH_METHODS}, got {self.search!r}")
        if not (isinstance(self.polish_runs, int) and self.polish_runs >= 0):
            raise ValueError(
                f"FitConfig.polish_runs must be a count >= 0 (0: every run), got {self.polish_runs!r}"
            )
        if not (isinstance(self.nm_window, int) and self.nm_window >= 0):
            raise ValueError(
                f"FitConfig.nm_window must be a step count >= 0 (0: no stall test), got {self.nm_window!r}"
            )
        if not self.nm_ftol >= 0:
            raise ValueError(f"FitConfig.nm_ftol must be >= 0 metres, got {self.nm_ftol!r}")
        if self.search == "halving":
            rung_sizes(1, 1, self.eta, self.initial_fraction)  # checks eta > 1, 0 < initial_fraction <= 1


SEARCH_METHODS = ("auto", "exhaustive", "halving")

AUTO_HALVING_RUNS = 300
"""search = "auto": the fewest runs it halves on. On a few hundred runs halving chooses the exhaustive
search's rules but, on a first run, is no faster (its rungs' compilations cost what it saves;
docs/fitting.md), so below 300 runs "auto" is the exhaustive search."""

AUTO_FIRST_RUNG_RUNS = 40
"""search = "auto": the fewest runs the halving's first rung screens every setting on. A first rung of a
few dozen runs already keeps the settings that the exhaustive search (or a larger first rung) would
fit, in the full fit and in every fold, for a fraction of the setting-runs (docs/fitting.md,
"Successive halving")."""


def resolve_search(config: FitConfig, n_runs: int) -> FitConfig:
    """The concrete search of `config` for a study of n_runs runs.

    "auto" becomes the exhaustive search below AUTO_HALVING_RUNS runs, else halving with the smallest
    initial_fraction eta^-K (K >= 1) whose first rung still screens on AUTO_FIRST_RUNG_RUNS runs (the
    exhaustive search where no K >= 1 does); the cost of halving's search is then about (K + 1) / eta^K
    of the exhaustive one's (e.g. 4,000 runs, eta 3: K = 4, f0 = 1/81, about 6 %). "exhaustive" and
    "halving" are returned as given. Resolved on the study's runs (not a fold's), so that every fold
    halves on the same rungs.
    """
    if config.search != "auto":
        return config
    ratio = n_runs / AUTO_FIRST_RUNG_RUNS
    k = math.floor(math.log(ratio) / math.log(config.eta) + 1e-9) if ratio >= 1 else 0
    if k < 1 or n_runs < AUTO_HALVING_RUNS:
        return replace(config, search="exhaustive")
    return replace(config, search="halving", initial_fraction=float(config.eta) ** -k)


@dataclass
class FitResult:
    """A fitted rule and how it was found.

    Attributes:
        space: the ParamSpace. values: [d] fitted free values. rule: the fitted rule.
        objective: hard objective (metres) on the fitting weights; failure_rate, coverage: weighted,
            over the runs the objective includes.
        stages: one dict per stage (search, nelder_mead, relaxed) with its objective and values.
        search: the batched search (per-run matrices), for reuse.
        unsupported_rate: weighted share of the fitting runs on which the fitted rule's replay leaves
            the log's support; n_unsupported: how many runs (of those with weight > 0).
        n_excluded: runs (with weight > 0) dropped from the objective (support="exclude"; else 0).
        cache: under the halving search, the per-run results it computed (cross-validation folds reuse
            them: jsve.fitting._crossval.cross_validate's `caches`); not saved with the study.
        results: the fitted setting's per-run results on every run ([1, R]: `judge`); not saved.
    """

    space: ParamSpace
    values: np.ndarray
    objective: float
    failure_rate: float
    coverage: float
    stages: list[dict]
    search: SearchResult | None = None
    unsupported_rate: float = 0.0
    n_unsupported: int = 0
    n_excluded: int = 0
    cache: RunLossCache | None = None
    results: SearchResult | None = None

    @property
    def rule(self):
        return self.space.rule(jnp.asarray(self.values))

    def params(self) -> dict[str, float]:
        """Every parameter of the rule by name (fixed, then free)."""
        return self.space.params(self.values)


def search_design(space: ParamSpace, config: FitConfig, starts: Sequence[np.ndarray] = ()) -> np.ndarray:
    """The fit's design: config.n_search points of the named design, plus presets and given starts."""
    values = np.asarray(
        space.values_from_unit(design(config.design, config.n_search, space.dim, seed=config.seed))
    )
    extra = list(preset_values(space).values()) if config.include_presets else []
    extra += [np.asarray(s, np.float64) for s in starts]
    if extra:
        values = np.concatenate([values, np.stack(extra)])
    return values


def fit_cache(data: FitData, space: ParamSpace, config: FitConfig) -> RunLossCache:
    """An empty cache of per-run results of the fit's design (search_design) on `data`."""
    return RunLossCache(data.scorer, space, search_design(space, config))


def search_all(data: FitData, space: ParamSpace, values, *, progress: bool = True, desc: str = "search"):
    """Every setting of `values` scored on every run of `data` (its scorer)."""
    return data.scorer.score(space, values, progress=progress, desc=desc)


def fit(
    data: FitData,
    space: ParamSpace,
    weights=None,
    config: FitConfig = FitConfig(),  # noqa: B008
    *,
    search_result: SearchResult | None = None,
    cache: RunLossCache | None = None,
    pool=None,
    progress: bool = True,
) -> FitResult:
    """Fit the free parameters of `space` to minimise the weighted hard objective over `data`.

    Arguments:
        weights: [R] run weights (jsve.evaluation.group_weights; 0 excludes a run, e.g. a held-out fold).
        search_result: a search already run on these data (cross-validation reuses one for all folds).
        cache: under config.search == "halving", per-run results of the fit's design computed so far
            (cross-validation shares one between folds); default a new one.
        pool: [R] the run weights Nelder-Mead's runs are drawn from (a fold: the study's weights, so it
            polishes on the full fit's polish runs less its held-out ones); default `weights`.
    Returns:
        FitResult; its stages record the objective after the search, Nelder-Mead and the relaxed fit.
    """
    w = _default_weights(data, weights)
    config = resolve_search(config, data.n_runs)
    t0 = time.perf_counter()
    if search_result is None:
        search_result, screening, cache = fit_search(data, space, w, config, cache=cache, progress=progress)
        method = config.search
    else:
        screening, method = {}, "given"
    pending = polish(
        data, space, w, search_result, config, method=method, search_seconds=time.perf_counter() - t0,
        screening=screening, pool=pool,
    )  # fmt: skip
    (result,) = judge(data, space, [pending], cache=cache)
    return result


def fit_search(
    data: FitData,
    space: ParamSpace,
    weights: np.ndarray,
    config: FitConfig,
    *,
    cache: RunLossCache | None = None,
    progress: bool = True,
) -> tuple[SearchResult, dict, RunLossCache | None]:
    """The fit's search under run weights: halving (on `cache`, a new one by default) or exhaustive, as
    config.search says once resolved for the study's size.

    Returns:
        (the search: every setting, or halving's survivors, on every run; halving's record of its rungs
        ({} for the exhaustive search); the cache of per-run results, None for the exhaustive search).
    """
    config = resolve_search(config, data.n_runs)
    if config.search != "halving":
        values = search_design(space, config)
        return search_all(data, space, values, progress=progress, desc=f"search {space.kind}"), {}, None
    if cache is None:
        cache = fit_cache(data, space, config)
    elif not np.array_equal(cache.values, search_design(space, config)):
        raise ValueError("fit: the cache holds another design than this fit's (search_design)")
    halving = halving_search(
        cache,
        np.asarray(weights, np.float64),
        eta=config.eta,
        initial_fraction=config.initial_fraction,
        order=stratified_order(data.meta, data.n_runs, seed=config.seed),
        progress=progress,
        desc=f"halving {space.kind}",
    )
    return halving.search, halving.as_dict(), cache


@dataclass
class PolishedFit:
    """A fit before its verdict: its search, its polishes' values, and the stages that record them.

    Attributes:
        weights: [R] the fit's run weights. search: the search it started from.
        stages: the search's, Nelder-Mead's and the relaxed fit's records (their objectives are set by
            `judge`, on every run with weight).
        candidates: (stage index, values [d]): the search's best (stage 0) and each polish's result.
    """

    weights: np.ndarray
    search: SearchResult
    stages: list[dict]
    candidates: list[tuple[int, np.ndarray]]


def polish(
    data: FitData,
    space: ParamSpace,
    weights: np.ndarray,
    search_result: SearchResult,
    config: FitConfig,
    *,
    method: str = "given",
    search_seconds: float = 0.0,
    screening: dict | None = None,
    pool=None,
) -> PolishedFit:
    """Nelder-Mead from the best searched settings (and the relaxed fit from the best so far), each
    moving on its own runs (`polish_runs`, drawn from `pool`); none of them judged on every run yet
    (`judge`)."""
    record = {"method": method, "seconds": search_seconds, **(screening or {})}
    return polish_fits(data, space, [(weights, search_result)], config, records=[record], pool=pool)[0]


def polish_fits(
    data: FitData,
    space: ParamSpace,
    searched: Sequence[tuple[np.ndarray, SearchResult]],
    config: FitConfig,
    *,
    records: Sequence[dict] | None = None,
    pool: np.ndarray | None = None,
    progress: bool = False,
    desc: str | None = None,
) -> list[PolishedFit]:
    """`polish` of many fits at once: the Nelder-Mead runs of all of them (config.n_starts a fit, from
    its search's best settings under its own weights) move in lockstep, each on its own polish runs
    (jsve.fitting._polish.polish_in_lockstep), so each step is one batched search for all of them.

    Arguments:
        searched: (run weights [R], its search) of each fit. records: extra fields of each fit's
            search stage (its method, seconds, halving record); default {"method": "given"}.
        pool: [R] the run weights every fit's polish runs are drawn from (the study's, for
            cross-validation folds: jsve.fitting._polish.polish_runs); default each fit's own.
    Returns:
        One PolishedFit per fit, in order; each Nelder-Mead stage records the lockstep's wall time
        (`seconds`, shared by `simplexes` runs).
    """
    records = list(records) if records is not None else [{"method": "given"}] * len(searched)
    pending, starts = [], []
    for f, ((weights, search_result), record) in enumerate(zip(searched, records, strict=True)):
        w = np.asarray(weights, np.float64)
        obj = search_result.objective(w)
        order = np.argsort(obj, kind="stable")
        best_values, best = search_result.values[order[0]], float(obj[order[0]])
        stage = {"stage": "search", "objective": best, "values": best_values.tolist(), "settings": len(obj),
                 "method": "given", "seconds": 0.0, **record}  # fmt: skip
        log.info("%s search: best %.5f m over %d settings", space.kind, best, len(obj))
        pending.append(PolishedFit(w, search_result, [stage], [(0, np.asarray(best_values, np.float64))]))
        starts += [(f, start) for start in search_result.values[order[: max(config.n_starts, 0)]]]
    release_memory()  # the searches' executables (one per part and rung shape) are not needed again
    if starts:
        ended = polish_in_lockstep(
            data, space, [p.weights for p in pending], starts, n_runs=config.polish_runs, seed=config.seed,
            step=config.nm_step, max_steps=config.nm_steps, window=config.nm_window, ftol=config.nm_ftol,
            pool=pool, progress=progress, desc=desc or f"Nelder-Mead {space.kind}, {len(starts)} simplexes",
        )  # fmt: skip
        counts = dict.fromkeys(range(len(pending)), 0)
        for k, (f, _) in enumerate(starts):
            fit_ = pending[f]
            fit_.candidates.append((len(fit_.stages), ended.values[k]))
            fit_.stages.append(
                {
                    "stage": f"nelder_mead_{counts[f]}",
                    "values": ended.values[k].tolist(),
                    "steps": int(ended.steps[k]),
                    "polish_runs": int(ended.polish_runs[k]),
                    "seconds": ended.seconds,
                    "simplexes": len(starts),
                }
            )
            counts[f] += 1
    if config.relaxed:
        for fit_ in pending:
            t1 = time.perf_counter()
            # from the best candidate so far, judged on every run (it starts where the simplex ended)
            start = judge(data, space, [fit_])[0].values
            values, history = relaxed_fit(
                data,
                space,
                start,
                fit_.weights,
                temperatures=config.temperatures,
                max_steps=config.bfgs_steps,
            )
            seconds = time.perf_counter() - t1
            fit_.candidates.append((len(fit_.stages), values))
            fit_.stages.append(
                {"stage": "relaxed", "values": values.tolist(), "history": history, "seconds": seconds}
            )
    return pending


def judge(
    data: FitData,
    space: ParamSpace,
    fits: Sequence[PolishedFit],
    *,
    cache: RunLossCache | None = None,
    progress: bool = False,
) -> list[FitResult]:
    """The verdict of many fits at once: every candidate of every fit (its search's best and each
    polish's result) scored on every run in one batched search, each fit's setting the candidate with the
    lowest objective on its own weights (ties to the earlier: the search's best before a polish). A
    polish that moved on a subset of the runs is judged on all of them.

    One search of all the distinct candidates fills the kernel's lanes (settings x runs):
    cross-validation's folds are judged together, not one setting per fold and pass over the study
    (docs/fitting.md).

    Returns:
        One FitResult per fit, in order, with `results`: the fitted setting's per-run results on every
        run ([1, R] matrices), which cross-validation scores its held-out runs by.
    """
    values = np.stack([v for f in fits for _, v in f.candidates])
    # Folds often share candidates (the same search best; a polish that ended where it started): each
    # distinct setting is scored once.
    distinct, inverse = np.unique(values, axis=0, return_inverse=True)
    scored = data.scorer.score(
        space,
        distinct,
        progress=progress,
        desc=f"verdict {space.kind}, {len(fits)} fits, {len(distinct)} settings",
    )
    everything = _rows(scored, np.asarray(inverse).reshape(-1))
    out, row = [], 0
    for f in fits:
        rows = np.arange(row, row + len(f.candidates))
        row += len(f.candidates)
        judged = everything.objective(f.weights)[rows]
        stages = [dict(stage) for stage in f.stages]
        best = 0
        for k, (stage, _) in enumerate(f.candidates):
            if stage > 0:
                stages[stage]["objective"] = float(judged[k])
                log.info("%s %s: %.5f m", space.kind, stages[stage]["stage"], judged[k])
            if judged[k] < judged[best]:
                best = k
        final = _rows(everything, rows[best : best + 1])
        w = f.weights
        weighted = w > 0
        n_unsupported = int(np.sum(final.unsupported[0] & weighted))
        n_excluded = int(np.sum(~final.included[0] & weighted))
        if n_unsupported:
            log.info(
                "%s fit: the fitted rule leaves the logs' support on %d of %d runs (%s: %d excluded)",
                space.kind, n_unsupported, int(weighted.sum()), data.config.support, n_excluded,
            )  # fmt: skip
        out.append(
            FitResult(
                space=space,
                values=np.asarray(f.candidates[best][1], np.float64),
                objective=float(final.objective(w)[0]),
                failure_rate=float(final.failure_rate(w)[0]),
                coverage=float(final.coverage_mean(w)[0]),
                stages=stages,
                search=f.search,
                unsupported_rate=float(final.unsupported_rate(w)[0]),
                n_unsupported=n_unsupported,
                n_excluded=n_excluded,
                cache=cache,
                results=final,
            )
        )
    return out


def _rows(result: SearchResult, rows: np.ndarray) -> SearchResult:
    return SearchResult(*(x[rows] for x in result.as_tuple()))


__all__ = [
    "FitData",
    "FitConfig",
    "FitResult",
    "fit",
    "fit_search",
    "polish",
    "polish_fits",
    "judge",
    "PolishedFit",
    "nelder_mead",
    "relaxed_fit",
    "hard_objective",
    "relaxed_objective",
    "search_design",
    "fit_cache",
    "search_all",
    "SEARCH_METHODS",
    "AUTO_FIRST_RUNG_RUNS",
    "AUTO_HALVING_RUNS",
    "resolve_search",
    "DEFAULT_TEMPERATURES",
]
