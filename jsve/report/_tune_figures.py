"""The tuning report's figures: held-out paired differences, and the replay against the front-end."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from jsve.report._figures import save

CM = 100.0


def figure_check(check: pd.DataFrame, path: Path) -> Path:
    """Per baseline and scope: the tuned rule's mean paired difference (cm) with its 95 % BCa interval,
    green or red where check_verdict says better or worse."""
    from jsve.tuning._race import check_verdict

    rows = check.reset_index(drop=True)
    fig, ax = plt.subplots(figsize=(7.5, 0.45 * len(rows) + 1.4))
    y = np.arange(len(rows))[::-1]
    for yi, r in zip(y, rows.itertuples(), strict=True):
        word = check_verdict(r._asdict())
        colour = {"better": "#2ca02c", "worse": "#d62728"}.get(word, "#444444")
        ax.errorbar(
            r.mean_diff_m * CM,
            yi,
            xerr=[
                [max(0.0, (r.mean_diff_m - r.bca_low_m) * CM)],
                [max(0.0, (r.bca_high_m - r.mean_diff_m) * CM)],
            ],
            fmt="o",
            color=colour,
            capsize=3,
        )
    ax.axvline(0, color="#888888", lw=1)
    ax.set_yticks(y, [f"vs {r.baseline}: {r.scope} (n={r.pairs})" for r in rows.itertuples()], fontsize=8)
    ax.set_xlabel(f"{rows['rule'].iloc[0]} - baseline\nbounded loss (cm); 95 % BCa")
    ax.set_title("Held-out paired differences (negative: the tuned rule is better)", fontsize=10)
    fig.tight_layout()
    return save(fig, path)


def figure_agreement(a: pd.DataFrame, path: Path) -> Path:
    """Predicted (replay) against measured (loop) difference to the incumbent per raced candidate (cm)."""
    fig, ax = plt.subplots(figsize=(5.2, 4.6))
    for origin, g in a.groupby("origin"):
        ax.scatter(g["predicted_diff_m"] * CM, g["measured_diff_m"] * CM, label=origin, s=28)
    lo = min(a["predicted_diff_m"].min(), a["measured_diff_m"].min(), 0) * CM
    hi = max(a["predicted_diff_m"].max(), a["measured_diff_m"].max(), 0) * CM
    pad = 0.05 * (hi - lo or 1)
    ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="#888888", lw=1, label="predicted = measured")
    ax.set_xlabel("replay: predicted difference to the incumbent (cm)")
    ax.set_ylabel("front-end: measured difference (cm)")
    ax.set_title("Replay against the front-end, per candidate", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save(fig, path)


__all__ = ["figure_agreement", "figure_check"]
