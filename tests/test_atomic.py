"""jsve.io._atomic: outputs appear complete under their final name or not at all."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from jsve.io import _atomic as atomic


@pytest.fixture
def table() -> pd.DataFrame:
    return pd.DataFrame(
        {"run": [3, 4], "rmse": [0.25, np.nan], "rule": ["orbslam3", "sve-option2"]}, index=[7, 9]
    )


def test_tables_by_suffix_without_the_index(table, tmp_path):
    csv = atomic.write_table(table, tmp_path / "out" / "runs.csv")
    assert csv.read_text() == "run,rmse,rule\n3,0.25,orbslam3\n4,,sve-option2\n"
    parquet = atomic.write_table(table, tmp_path / "out" / "runs.parquet")
    pd.testing.assert_frame_equal(pd.read_parquet(parquet), table.reset_index(drop=True))
    short = atomic.write_table(table, tmp_path / "short.csv", float_format="%.1f")
    assert short.read_text().splitlines()[1] == "3,0.2,orbslam3"  # 0.25 to one decimal, half to even
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["runs.csv", "runs.parquet"]


def test_list_valued_metadata_round_trips_through_csv_as_json_lists(tmp_path):
    """run_meta_table keeps list-valued metadata as tuples (groupable); runs.csv (jsve evaluate, jsve
    fit) writes them as JSON lists, which any CSV reader can parse, and read_table gives the tuples back;
    other text, even text that starts with '[', stays as it was."""
    from logfactory import make_run

    from jsve.io._batching import run_meta_table

    runs = [
        make_run(20, k, sequence="S", run=k, image_size=[752, 480], gravity=[0.0, 0.0, -9.81], note="[draft")
        for k in range(2)
    ]
    meta = run_meta_table(runs)
    meta["mixed"] = [("a", 1), "plain"]
    assert meta.loc[0, "image_size"] == (752, 480)
    path = atomic.write_table(meta, tmp_path / "runs.csv")
    rows = pd.read_csv(path)  # a plain reader sees JSON
    assert json.loads(rows.loc[0, "gravity"]) == [0.0, 0.0, -9.81]
    assert rows.loc[0, "image_size"] == "[752, 480]" and rows.loc[0, "mixed"] == '["a", 1]'
    back = atomic.read_table(path)
    for column in ("image_size", "gravity", "mixed", "note", "sequence"):
        assert back[column].tolist() == meta[column].tolist(), column
    assert meta.loc[0, "image_size"] == (752, 480)  # the caller's table is not changed


def test_a_failed_write_leaves_the_old_file_and_no_partial(table, tmp_path, monkeypatch):
    path = atomic.write_table(table, tmp_path / "runs.csv")
    before = path.read_bytes()

    def die(self, *args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(pd.DataFrame, "to_csv", die)
    with pytest.raises(OSError, match="disk full"):
        atomic.write_table(table.iloc[:1], path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["runs.csv"]


def test_json_is_indented_sorted_and_takes_numpy_values(tmp_path):
    path = atomic.write_json(
        tmp_path / "study.json", {"b": np.float64(0.5), "a": np.arange(3), "n": np.int32(2)}
    )
    text = path.read_text()
    assert text.endswith("}\n") and text.index('"a"') < text.index('"b"')
    assert json.loads(text) == {"a": [0, 1, 2], "b": 0.5, "n": 2}
    assert text == json.dumps({"a": [0, 1, 2], "b": 0.5, "n": 2}, indent=2, sort_keys=True) + "\n"
