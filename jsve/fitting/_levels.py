"""The SVE level table: how each SVE score and metric moves with the disturbance level (seed Figs 4-6).

Per (disturbance, level, combination) it gives the number of valid frames and the mean and standard
deviation over them of the combination's score and of every SVE metric (jsve.core._sve.feature_metrics:
S_a at the combination's rho, S_b, S_c and the authors' unclamped variants).

`SveLevelSums` accumulates it chunk by chunk, so that it rides on a pass over the study that happens
anyway (`jsve fit`'s evaluation, jsve.evaluation._evaluate.evaluate_rules' `on_chunk`) instead of
streaming the study again. A chunk gives per run, in one compiled call, the valid frames, the mean
and the sum of squared deviations from that mean; runs are pooled on the host in float64 (Chan, Golub
& LeVeque's pairwise update), which keeps the variance free of the cancellation of sum(x^2) - n mean^2
in float32.
"""

from __future__ import annotations

from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pandas as pd

from jsve.core._batch import LogBatch
from jsve.core._sve import Combination, FrameFeatures, feature_metrics, metric_names


@eqx.filter_jit
def _run_moments(features: FrameFeatures, valid, combinations: Mapping[str, Combination]):
    """Per run ([R, T] inputs): valid frames [R], and per (combination, value) the mean [R] and the sum
    of squared deviations from it [R] over the valid frames."""
    w = valid.astype(features.s_b.dtype)
    n = jnp.sum(w, axis=-1)
    out = {}
    for name, combo in combinations.items():
        values = {"sve": combo.score(features), **feature_metrics(features, combo.rho)}
        for key, x in values.items():
            x = jnp.where(valid, x, 0.0)  # padding frames may hold anything
            mean = jnp.sum(x * w, axis=-1) / jnp.maximum(n, 1.0)
            out[name, key] = (mean, jnp.sum(jnp.square((x - mean[:, None]) * w), axis=-1))
    return n, out


class SveLevelSums:
    """The SVE level table, accumulated one chunk of runs at a time (`add`), read with `table`."""

    def __init__(self, combinations: Mapping[str, Combination]):
        self.combinations = dict(combinations)
        self._meta: list[pd.DataFrame] = []
        self._n: list[np.ndarray] = []
        self._moments: list[dict] = []

    def add(self, meta: pd.DataFrame, batch: LogBatch, features: FrameFeatures) -> None:
        """Add a chunk: `meta` holds its real runs (disturbance and level columns), which come first in
        `batch` and `features` ([R, T]; the runs after them are padding and are ignored)."""
        n_real = len(meta)
        n, moments = _run_moments(features, jnp.asarray(batch.valid), self.combinations)
        self._meta.append(meta[["disturbance", "level"]])
        self._n.append(np.asarray(n, np.float64)[:n_real])
        host = lambda pair: tuple(np.asarray(a, np.float64)[:n_real] for a in pair)  # noqa: E731
        self._moments.append({key: host(pair) for key, pair in moments.items()})

    def table(self) -> pd.DataFrame:
        """One row per (combination, disturbance, level) in that order, levels sorted: disturbance,
        level, combination, frames, then <value>_mean and <value>_std for "sve" and every metric
        (population standard deviation over the valid frames)."""
        columns = ["disturbance", "level", "combination", "frames"]
        if not self._meta:
            return pd.DataFrame(columns=columns)
        meta = pd.concat(self._meta, ignore_index=True)
        n = np.concatenate(self._n)
        groups = meta.groupby(["disturbance", "level"], sort=True).indices
        rows = []
        for name in self.combinations:
            keys = ["sve", *metric_names()]  # (the compiled call's dict comes back in sorted order)
            mean = {k: np.concatenate([m[name, k][0] for m in self._moments]) for k in keys}
            m2 = {k: np.concatenate([m[name, k][1] for m in self._moments]) for k in keys}
            for dist, level in sorted(groups):
                idx = groups[dist, level]
                n_g = n[idx].sum()
                row = {"disturbance": dist, "level": level, "combination": name, "frames": int(n_g)}
                for k in keys:
                    pooled = np.sum(n[idx] * mean[k][idx]) / n_g if n_g > 0 else np.nan
                    spread = np.sum(m2[k][idx]) + np.sum(n[idx] * (mean[k][idx] - pooled) ** 2)
                    row[f"{k}_mean"] = pooled
                    row[f"{k}_std"] = float(np.sqrt(spread / n_g)) if n_g > 0 else np.nan
                rows.append(row)
        return pd.DataFrame(rows)


def sve_level_table(data, combinations: Mapping[str, Combination]) -> pd.DataFrame:
    """`SveLevelSums.table` of FitData `data` in a pass of its own over its slim batches (streamed again
    where they were not kept)."""
    sums, start = SveLevelSums(combinations), 0
    for batch, features, n_real in data.iter_slim():
        sums.add(data.meta.iloc[start : start + n_real], batch, features)
        start += n_real
    return sums.table()


__all__ = ["SveLevelSums", "sve_level_table"]
