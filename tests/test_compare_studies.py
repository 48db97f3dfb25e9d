"""analysis/compare_studies.py: the held-out comparison of two studies' fitted rules on the same runs."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest


def _script():
    path = Path(__file__).resolve().parents[1] / "analysis" / "compare_studies.py"
    spec = importlib.util.spec_from_file_location("analysis_compare_studies", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _folder(path: Path, losses: dict[str, np.ndarray], fingerprint: str = "abc") -> Path:
    """A finished study's files as compare_studies reads them: held-out losses per rule on 40 runs."""
    path.mkdir()
    rows = []
    for rule, loss in losses.items():
        for i, x in enumerate(loss):
            rows.append({"fold_kind": "kfold", "run_index": i, "rule": rule, "weight": 1.0, "loss": x,
                         "failed": False, "coverage": 1.0})  # fmt: skip
    pd.DataFrame(rows).to_parquet(path / "heldout.parquet")
    (path / "study.json").write_text(json.dumps({"data_fingerprint": fingerprint}))
    stages = {"cross_validation": {"seconds": 60.0, "peak_rss_gb": 2.5}}
    (path / "stages.json").write_text(json.dumps({"done": stages}))
    return path


def test_the_second_study_is_compared_run_by_run_with_the_first(tmp_path, capsys):
    script = _script()
    rng = np.random.default_rng(0)
    base = rng.uniform(0.05, 0.5, 40)
    a = _folder(tmp_path / "a", {"fitted-sve": base, "fitted-inliers": base + 0.1, "orbslam3": base})
    b = _folder(tmp_path / "b", {"fitted-sve": base + 0.01, "fitted-inliers": base + 0.1})
    table = script.comparison([a, b], ["halving", "exhaustive"], n_boot=200).set_index("rule")
    assert set(table.index) == {
        "fitted-sve@halving",
        "fitted-sve@exhaustive",
        "fitted-inliers@halving",
        "fitted-inliers@exhaustive",
    }  # fmt: skip (presets are left out)
    sve = table.loc["fitted-sve@exhaustive"]
    assert sve["diff_vs_halving"] == pytest.approx(0.01)  # paired: every run 1 cm worse, CI 0 wide
    assert sve["diff_vs_halving_ci_low"] == pytest.approx(0.01)
    assert table.loc["fitted-inliers@exhaustive", "diff_vs_halving"] == pytest.approx(0.0)
    assert np.isnan(table.loc["fitted-sve@halving", "diff_vs_halving"])
    assert table.loc["fitted-sve@halving", "mean_loss"] == pytest.approx(base.mean())

    assert script.main([str(a), str(b), "--names", "halving", "exhaustive"]) == 0
    assert "peak RSS 2.50 GB" in capsys.readouterr().out
    c = _folder(tmp_path / "c", {"fitted-sve": base}, fingerprint="other")
    with pytest.raises(SystemExit, match="different data"):
        script.main([str(a), str(c)])
