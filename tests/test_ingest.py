"""jsve.io._ingest and `jsve ingest`: many logs in parallel with quarantine, Parquet, load_runs, and
v1 logs (one summary warning) among v2 logs."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from logfactory import edit_line, make_run, same_bits, set_field, v1_text

from jsve.cli import ingest as ingest_cli
from jsve.io import _ingest as ingest
from jsve.io import _logs as logs
from jsve.io import _parquet as parquet
from jsve.io import _schema as schema
from jsve.io._errors import LogVersionWarning
from jsve.io._groundtruth import GroundTruth
from jsve.io._logs import LogFormatError

N = 20  # frames of the small logs below


def same_runs(a: list[schema.RunLog], b: list[schema.RunLog]) -> bool:
    return len(a) == len(b) and all(
        x.meta == y.meta and x.source == y.source and same_bits(x.frames, y.frames)
        for x, y in zip(a, b, strict=True)
    )


# ---------------------------------------------------------------------------------------------------
# Many logs


@pytest.fixture
def logdir(tmp_path) -> tuple[Path, list[str], list[str]]:
    """18 good logs in three folders and four broken ones: (dir, good paths, bad paths), sorted."""
    root = tmp_path / "logs"
    good = [
        logs.write_log(
            make_run(30 + i, i, with_gt=i % 3 != 0, sequence="MH_04"), root / f"d{i % 3}" / f"r{i:02d}.csv"
        )
        for i in range(18)
    ]
    bad = []
    p = logs.write_log(make_run(30, 100, sequence="MH_04"), root / "d0" / "r50.csv")
    set_field(p, 9, "imu_dt", "-0.05")
    bad.append(p)
    p = logs.write_log(make_run(30, 101, sequence="MH_04"), root / "d1" / "r51.csv")
    edit_line(p, 33, None)  # end marker gone
    bad.append(p)
    p = logs.write_log(make_run(30, 102, sequence="MH_04"), root / "d2" / "r52.csv")
    bad.append(p.rename(p.with_name("r52.csv.partial")))
    p = root / "notes.csv"
    p.write_text("a,b\n1,2\n")
    bad.append(p)
    (root / "README.txt").write_text("not a log, not read")
    return root, sorted(map(str, good)), sorted(map(str, bad))


def test_quarantine_lists_exactly_the_broken_logs(logdir):
    root, good, bad = logdir
    result = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in result.runs] == good
    assert [q.path for q in result.quarantined] == bad
    by_path = {q.path: q for q in result.quarantined}
    assert by_path[bad[0]].line == 9 and by_path[bad[0]].column == "imu_dt"
    assert [by_path[p].incomplete for p in bad] == [False, True, True, False]
    report = result.report()
    assert list(report.columns) == list(ingest.QUARANTINE_COLUMNS)
    assert report["path"].tolist() == bad
    assert report["message"].tolist() == [q.message for q in result.quarantined]


def test_quarantine_report_csv(logdir, tmp_path):
    root, _, bad = logdir
    result = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    path = ingest.write_quarantine_report(result, tmp_path / "q.csv")
    back = pd.read_csv(path)
    assert back["path"].tolist() == bad
    assert back["message"].tolist() == result.report()["message"].tolist()


def test_raise_stops_at_the_first_bad_log_in_sorted_order(logdir):
    root, _, bad = logdir
    for workers in (1, 2):
        with pytest.raises(LogFormatError) as info:
            ingest.read_logs(root, workers=workers, progress=False)
        assert info.value.path == bad[0]
        assert info.value.line == 9


def test_parallel_read_equals_serial_read(logdir):
    root, good, _ = logdir
    serial = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    parallel = ingest.read_logs(root, on_error="quarantine", workers=2, progress=False)
    assert same_runs(serial.runs, parallel.runs)
    assert serial.quarantined == parallel.quarantined
    assert len(parallel.runs) == len(good)


def test_sources_glob_list_and_file(logdir):
    root, good, _ = logdir
    by_glob = ingest.read_logs(str(root / "d1" / "r*.csv"), on_error="quarantine", workers=1, progress=False)
    in_d1 = [p for p in good if "/d1/" in p]
    assert [r.source for r in by_glob.runs] == in_d1 and len(by_glob.quarantined) == 1
    by_list = ingest.read_logs(list(reversed(in_d1)), workers=1, progress=False)
    assert [r.source for r in by_list.runs] == in_d1
    assert ingest.find_logs(good[0]) == [good[0]]
    with pytest.raises(FileNotFoundError):
        ingest.find_logs(root / "nothing-here")
    with pytest.raises(FileNotFoundError):
        ingest.find_logs(str(root / "*.nope"))


def test_duplicate_run_ids_name_both_files(tmp_path):
    a = logs.write_log(make_run(N, 1, sequence="V101"), tmp_path / "a.csv")
    b = logs.write_log(make_run(N, 1, sequence="V101"), tmp_path / "b.csv")
    with pytest.raises(LogFormatError) as info:
        ingest.read_logs(tmp_path, workers=1, progress=False)
    assert info.value.path == str(b) and str(a) in str(info.value)
    assert "duplicate run id: 'V101/none-0/1'" in str(info.value)
    result = ingest.read_logs(tmp_path, on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in result.runs] == [str(a)]
    assert [q.path for q in result.quarantined] == [str(b)]


def test_runs_of_several_rules_in_the_loop_have_their_own_ids(tmp_path):
    """One setting run under ORB-SLAM3's rule, under `record` and under a rule named by JSON only."""
    stock = make_run(N, 1, sequence="V101", rule="orbslam3", switch_model="orbslam3")
    record = make_run(
        N, 1, sequence="V101", rule='{"kind": "inliers"}', rule_name="record", switch_model="imu-coast"
    )
    unnamed = make_run(N, 1, sequence="V101", rule='{"kind": "inliers"}', switch_model="orbslam3")
    for name, run in (("a", stock), ("b", record), ("c", unnamed)):
        logs.write_log(run, tmp_path / f"{name}.csv")
    ids = sorted(r.run_id for r in ingest.read_logs(tmp_path, workers=1, progress=False).runs)
    assert ids == ["V101/none-0/1", "V101/none-0/record-imu-coast/1", "V101/none-0/rule-24d2fcdb-orbslam3/1"]


def test_unreadable_paths_are_quarantined_not_lost(tmp_path):
    good = logs.write_log(make_run(N, 1), tmp_path / "a.csv")
    gone = tmp_path / "gone.csv"
    result = ingest.read_logs([good, gone], on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in result.runs] == [str(good)]
    (q,) = result.quarantined
    assert q.path == str(gone) and "cannot read the file" in q.message
    empty = ingest.ReadResult(runs=result.runs).report()
    assert list(empty.columns) == list(ingest.QUARANTINE_COLUMNS) and len(empty) == 0


def test_progress_bar_goes_to_stderr(tmp_path, capsys):
    for i in range(3):
        logs.write_log(make_run(N, i), tmp_path / f"r{i}.csv")
    ingest.read_logs(tmp_path, workers=1, progress=True)
    captured = capsys.readouterr()
    assert captured.out == "" and "3/3" in captured.err
    ingest.read_logs(tmp_path, workers=1, progress=False)
    assert capsys.readouterr().err == ""


def test_on_error_is_checked(logdir):
    with pytest.raises(ValueError, match="on_error"):
        ingest.read_logs(logdir[0], on_error="skip", progress=False)


# ---------------------------------------------------------------------------------------------------
# Parquet


def test_ingest_and_read_parquet_round_trip(logdir, tmp_path):
    root, good, bad = logdir
    out = tmp_path / "study.parquet"
    summary = parquet.ingest(root, out, on_error="quarantine", workers=2, progress=False)
    expected = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    assert summary.n_runs == len(good) and summary.n_frames == sum(len(r.frames) for r in expected.runs)
    assert [q.path for q in summary.quarantined] == bad
    assert summary.quarantine_report == tmp_path / "study.quarantine.csv"
    assert pd.read_csv(summary.quarantine_report)["path"].tolist() == bad
    assert same_runs(parquet.read_parquet(out), expected.runs)
    assert not any(p.name.endswith(".partial") for p in tmp_path.iterdir())

    pf = pq.ParquetFile(out)
    assert pf.schema_arrow.names[:2] == ["run_id", "frame"]
    assert pf.schema_arrow.names[2:] == [*schema.COLUMNS, *schema.WORLD_COLUMNS, "in_saved"]
    assert str(pf.schema_arrow.field("frame").type) == "int32"
    assert str(pf.schema_arrow.field("run_id").type).startswith("dictionary<values=string")
    entries = json.loads(pf.metadata.metadata[b"jsve.runs"])
    assert [e["run_id"] for e in entries] == [r.run_id for r in expected.runs]
    assert [e["meta"] for e in entries] == [r.meta for r in expected.runs]
    table = pq.read_table(out, columns=["run_id", "frame", "t_ns"])
    first = expected.runs[0]
    assert table.column("run_id")[0].as_py() == first.run_id
    assert table.column("t_ns").to_numpy()[: len(first.frames)].tolist() == first.frames["t_ns"].tolist()


def test_ingest_raise_writes_nothing(logdir, tmp_path):
    out = tmp_path / "study.parquet"
    with pytest.raises(LogFormatError):
        parquet.ingest(logdir[0], out, workers=1, progress=False)
    assert list(tmp_path.iterdir()) == [logdir[0]]


def test_ingest_without_bad_logs_writes_no_report(tmp_path):
    for i in range(3):
        logs.write_log(make_run(N, i), tmp_path / "logs" / f"r{i}.csv")
    out = tmp_path / "out" / "s.parquet"
    stale = out.with_suffix(".quarantine.csv")
    stale.parent.mkdir()
    stale.write_text("path\nold.csv\n")
    summary = parquet.ingest(tmp_path / "logs", out, on_error="quarantine", workers=1, progress=False)
    assert summary.quarantine_report is None and summary.n_runs == 3
    assert not stale.exists()  # a report from an earlier ingest would describe other logs


def test_read_parquet_rejects_other_parquet(tmp_path):
    path = tmp_path / "x.parquet"
    pd.DataFrame({"a": [1, 2]}).to_parquet(path)
    with pytest.raises(LogFormatError, match="not a jsve Parquet file"):
        parquet.read_parquet(path)


def test_load_runs_reads_a_parquet_file_or_logs_alike(logdir, tmp_path):
    root, good, bad = logdir
    out = tmp_path / "study.parquet"
    parquet.ingest(root, out, on_error="quarantine", workers=1, progress=False)
    from_logs = parquet.load_runs(root, on_error="quarantine", workers=1, progress=False)
    from_parquet = parquet.load_runs(str(out))
    assert [q.path for q in from_logs.quarantined] == bad and from_parquet.quarantined == []
    assert [r.source for r in from_logs.runs] == good
    assert same_runs(from_parquet.runs, from_logs.runs)
    assert same_runs(parquet.load_runs(out).runs, from_logs.runs)  # a Path as well as a str
    with pytest.raises(LogFormatError):
        parquet.load_runs(root, workers=1, progress=False)  # on_error="raise" by default


def test_partial_files_are_never_skipped(tmp_path):
    logs.write_log(make_run(N, 1), tmp_path / "a.csv")
    os.rename(logs.write_log(make_run(N, 2), tmp_path / "b.csv"), tmp_path / "b.csv.partial")
    result = ingest.read_logs(tmp_path, on_error="quarantine", workers=1, progress=False)
    assert [q.path for q in result.quarantined] == [str(tmp_path / "b.csv.partial")]
    assert result.quarantined[0].incomplete and "incomplete" in result.quarantined[0].message


# ---------------------------------------------------------------------------------------------------
# jsve ingest


def cli(argv: list[str]) -> int:
    """`jsve ingest ...` through the subcommand's own parser (the other subcommands are not needed)."""
    parser = argparse.ArgumentParser(prog="jsve")
    ingest_cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_ingest(logdir, tmp_path, capsys):
    root, good, bad = logdir
    out = tmp_path / "s.parquet"
    assert cli(["ingest", str(root), "-o", str(out), "--workers", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"{bad[0]}:9: column 'imu_dt' = '-0.05': must be >= 0" in err and not out.exists()

    report = tmp_path / "bad.csv"
    argv = [
        "ingest",
        str(root),
        "-o",
        str(out),
        "--on-error",
        "quarantine",
        "--quarantine-report",
        str(report),
    ]
    assert cli([*argv, "--workers", "1", "--no-progress"]) == 0
    line = capsys.readouterr().out.strip()
    assert re.search(rf"ingested {len(good)} runs, \d+ frames -> .*; quarantined {len(bad)}", line)
    assert len(parquet.read_parquet(out)) == len(good) and pd.read_csv(report)["path"].tolist() == bad


def test_cli_usage_errors(tmp_path):
    with pytest.raises(SystemExit):
        cli(["ingest", str(tmp_path), "-o", "x.parquet", "--quarantine-report", "q.csv"])
    with pytest.raises(SystemExit):
        cli(["ingest", str(tmp_path), "-o", "x.parquet", "--gt", "a.txt", "--kitti-times", "t.txt"])


def test_no_logs_is_an_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError):
        parquet.ingest(tmp_path / "empty", tmp_path / "s.parquet", progress=False)
    assert cli(["ingest", str(tmp_path / "empty"), "-o", str(tmp_path / "s.parquet"), "--no-progress"]) == 2


# ---------------------------------------------------------------------------------------------------
# Format v2 columns and v1 logs in a batch


@pytest.fixture
def mixed_versions(tmp_path) -> tuple[Path, list[str]]:
    """20 logs: 15 v2 (some frames without a pose, several maps) and 5 v1; (dir, v1 paths sorted)."""
    root = tmp_path / "mixed"
    v1 = []
    for i in range(20):
        if i % 4 == 1:
            p = logs.write_log(make_run(40 + i, i, sequence="V101"), root / f"r{i:02d}.csv")
            v1_text(p)
            v1.append(str(p))
        else:
            map_id = np.repeat([0, i], [20, 20 + i])
            logs.write_log(
                make_run(40 + i, i, no_pose=0.4, map_id=map_id, sequence="V101"), root / f"r{i:02d}.csv"
            )
    return root, v1


@pytest.mark.parametrize("workers", [1, 2])
def test_v1_logs_in_a_batch_give_one_summary_warning(mixed_versions, workers):
    root, v1 = mixed_versions
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        result = ingest.read_logs(root, workers=workers, progress=False)
    versions = [w for w in record if issubclass(w.category, LogVersionWarning)]
    assert len(versions) == 1, [str(w.message) for w in record]
    message = str(versions[0].message)
    assert message.startswith(
        "5 v1 logs read with defaults: map_id = 0, imu_ba2 = imu_init & (t - t_first >= 15 s)"
    )
    assert f"({v1[0]}, {v1[1]}, {v1[2]} and 2 more;" in message
    assert versions[0].filename == __file__
    # Each run is what read_log gives alone (defaults for v1, map ids and NaN poses for v2).
    for run in result.runs:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LogVersionWarning)
            alone = logs.read_log(run.source)
        assert same_bits(run.frames, alone.frames)
    by_source = {r.source: r for r in result.runs}
    assert all(by_source[p].frames["map_id"].eq(0).all() for p in v1)
    assert sum(r.frames["vis_px"].isna().any() for r in result.runs) >= 10


def test_a_batch_of_v2_logs_warns_nothing(logdir):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ingest.read_logs(logdir[0], on_error="quarantine", workers=1, progress=False)


def test_ingest_carries_map_columns_and_missing_poses(mixed_versions, tmp_path):
    root, v1 = mixed_versions
    out = tmp_path / "s.parquet"
    with pytest.warns(LogVersionWarning, match="^5 v1 logs read with defaults") as record:
        parquet.ingest(root, out, workers=1, progress=False)
    assert len([w for w in record if issubclass(w.category, LogVersionWarning)]) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LogVersionWarning)
        expected = ingest.read_logs(root, workers=1, progress=False).runs
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a format-2 Parquet file reads without a warning
        back = parquet.read_parquet(out)
    assert same_runs(back, expected)  # map_id, imu_ba2 exact; NaN poses bit for bit
    pf = pq.ParquetFile(out)
    assert pf.schema_arrow.names[2:7] == ["t_ns", "state", "imu_init", "map_id", "imu_ba2"]
    assert pf.metadata.metadata[b"jsve.format"] == b"3"
    entries = json.loads(pf.metadata.metadata[b"jsve.runs"])
    assert [e["source"] for e in entries if e["log_version"] == 1] == v1
    assert sum(e["log_version"] == schema.FORMAT_VERSION for e in entries) == 15


def _as_format_1(path: Path, out: Path) -> None:
    """A Parquet file as `ingest` wrote it before format v2: no map_id / imu_ba2, jsve.format "1"."""
    _rewrite(path, out, b"1", list(schema.MAP_COLUMNS))


def _rewrite(path: Path, out: Path, version: bytes, drop: list[str]) -> None:
    table = pq.read_table(path).drop_columns(drop)
    kv = {k: v for k, v in pq.ParquetFile(path).metadata.metadata.items() if k.startswith(b"jsve.")}
    kv[b"jsve.format"] = version
    pq.write_table(table.replace_schema_metadata(kv), out)


def test_parquet_of_format_1_reads_with_v1_defaults(tmp_path):
    for i in range(3):
        logs.write_log(make_run(400, i, sequence="MH_04"), tmp_path / "logs" / f"r{i}.csv")
    out = tmp_path / "s.parquet"
    parquet.ingest(tmp_path / "logs", out, workers=1, progress=False)
    old = tmp_path / "old.parquet"
    _as_format_1(out, old)
    with pytest.warns(LogVersionWarning) as record:
        runs = parquet.read_parquet(old)
    (w,) = record
    assert str(w.message).startswith(
        f"{old}: jsve Parquet file of format 1 (ingested before format v2): its 3 runs"
    )
    assert "map_id = 0, imu_ba2 = imu_init & (t - t_first >= 15 s)" in str(w.message)
    assert w.filename == __file__
    fresh = parquet.read_parquet(out)
    for a, b in zip(runs, fresh, strict=True):
        assert list(a.frames.columns) == list(schema.COLUMNS)
        assert a.frames["map_id"].eq(0).all()
        t = a.frames["t_ns"].to_numpy()
        expected = (a.frames["imu_init"].to_numpy() == 1) & (t - t[0] >= 15_000_000_000)
        assert np.array_equal(a.frames["imu_ba2"].to_numpy(), expected.astype(np.int64))
        others = [c for c in schema.COLUMNS if c not in schema.MAP_COLUMNS]
        assert same_bits(a.frames[others], b.frames[others])
    with pytest.warns(LogVersionWarning):
        assert same_runs(parquet.load_runs(old).runs, runs)


def test_parquet_of_an_unknown_format_is_refused(tmp_path):
    logs.write_log(make_run(N, 1), tmp_path / "logs" / "r.csv")
    out = tmp_path / "s.parquet"
    parquet.ingest(tmp_path / "logs", out, workers=1, progress=False)
    _rewrite(out, tmp_path / "x.parquet", b"4", [])
    with pytest.raises(LogFormatError, match="unsupported jsve Parquet format '4'.*reads 1 and 2 and 3"):
        parquet.read_parquet(tmp_path / "x.parquet")
    _rewrite(out, tmp_path / "y.parquet", b"2", ["imu_ba2"])
    with pytest.raises(LogFormatError, match="without the column.*imu_ba2"):
        parquet.read_parquet(tmp_path / "y.parquet")


# ---------------------------------------------------------------------------------------------------
# What a directory search finds (issue 12)


def test_a_folder_search_finds_gzip_and_upper_case_logs_and_names_the_rest(tmp_path, caplog):
    import gzip

    plain = logs.write_log(make_run(N, 1), tmp_path / "a.csv")
    upper = logs.write_log(make_run(N, 2), tmp_path / "B.CSV")
    packed = tmp_path / "sub" / "c.csv.gz"
    packed.parent.mkdir()
    packed.write_bytes(gzip.compress(logs.write_log(make_run(N, 3), tmp_path / "c.tmp").read_bytes()))
    cut = tmp_path / "d.csv.gz.partial"
    cut.write_bytes(b"")
    (tmp_path / "a.keypoints.csv").write_text("side file\n")  # jsve's own: skipped without a word
    (tmp_path / "notes.txt").write_text("not a log\n")
    with caplog.at_level("WARNING", logger="jsve.io._ingest"):
        found = ingest.find_logs(tmp_path)
    assert found == sorted(map(str, [plain, upper, packed, cut]))
    (record,) = caplog.records
    assert f"{tmp_path}: skipped 2 files that are not logs" in record.getMessage()
    assert "c.tmp, notes.txt" in record.getMessage()  # named, relative to the folder

    result = ingest.read_logs(tmp_path, on_error="quarantine", workers=1, progress=False)
    assert [r.meta["run"] for r in result.runs] == [2, 1, 3]  # sorted by path: B.CSV, a.csv, sub/c.csv.gz
    (q,) = result.quarantined
    assert q.path == str(cut) and q.incomplete


@pytest.mark.parametrize(
    "name, is_log",
    [
        ("r1.csv", True), ("R1.CSV", True), ("r1.csv.gz", True), ("r1.CSV.GZ", True),
        ("r1.csv.partial", True), ("r1.csv.gz.partial", True), ("r1.tsv", False), ("r1.gz", False),
        ("r1.keypoints.csv", False), ("out.quarantine.csv", False), ("r1.keypoints.csv.gz", False),
    ],
)  # fmt: skip
def test_log_names(name, is_log):
    assert ingest.is_log_name(name) is is_log


# ---------------------------------------------------------------------------------------------------
# The Parquet layout: both routes of a log (Arrow rows, RunLog frames) give the same file contents


def _with_world(run: schema.RunLog, seed: int) -> schema.RunLog:
    """The run with world_* columns: a random similarity per frame (unit quaternion, scale > 0)."""
    rng = np.random.default_rng(seed)
    frames = run.frames.copy()
    q = rng.normal(size=(len(frames), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    values = np.concatenate([q, rng.normal(size=(len(frames), 3)), rng.uniform(0.5, 2, (len(frames), 1))], 1)
    for k, c in enumerate(schema.WORLD_COLUMNS):
        frames[c] = values[:, k]
    return schema.RunLog(meta=run.meta, frames=frames, source=run.source)


def test_ingest_writes_every_column_group_as_the_frames_hold_it(tmp_path):
    root = tmp_path / "logs"
    logs.write_log(make_run(30, 0, sequence="V101"), root / "a.csv")  # gt_*
    logs.write_log(make_run(30, 1, with_gt=False, sequence="V101"), root / "b.csv")  # none
    logs.write_log(_with_world(make_run(30, 2, gt_missing=0.3, no_pose=0.3), 2), root / "c.csv")  # all
    logs.write_log(_with_world(make_run(30, 3, with_gt=False, sequence="V101"), 3), root / "d.csv")
    out = tmp_path / "s.parquet"
    parquet.ingest(root, out, workers=1, progress=False)
    expected = ingest.read_logs(root, workers=1, progress=False).runs
    assert [r.has_world_frame for r in expected] == [False, False, True, True]
    assert same_runs(parquet.read_parquet(out), expected)
    table = pq.read_table(out)
    rows = np.cumsum([0] + [len(r.frames) for r in expected])
    # A group a run lacks is null; a frame without a value (pose, ground truth) is NaN, never null.
    for k, run in enumerate(expected):
        part = table.slice(rows[k], rows[k + 1] - rows[k])
        for names, has in (
            (schema.GT_COLUMNS, run.has_ground_truth),
            (schema.WORLD_COLUMNS, run.has_world_frame),
        ):
            assert all(part.column(c).null_count == (0 if has else len(run.frames)) for c in names)
        assert part.column("vis_px").null_count == 0


def test_ingest_with_ground_truth_equals_reading_with_it(shared_data, tmp_path):
    gt_path = shared_data / "euroc" / "groundtruth_left_cam" / "V101_GT.txt"
    lines = [line for line in gt_path.read_text().splitlines() if not line.startswith("#")]
    stamps = np.array([int(line.split(",")[0].split(".")[0]) for line in lines[100:140]], dtype=np.int64)
    run = make_run(40, 1, with_gt=False, sequence="V101")
    logs.write_log(dataclasses.replace(run, frames=run.frames.assign(t_ns=stamps)), tmp_path / "a.csv")
    spec = {"V101": GroundTruth(gt_path, "euroc")}
    parquet.ingest(tmp_path, tmp_path / "s.parquet", ground_truth=spec, workers=1, progress=False)
    expected = ingest.read_logs(tmp_path, ground_truth=spec, workers=1, progress=False).runs
    back = parquet.read_parquet(tmp_path / "s.parquet")
    assert back[0].has_ground_truth and back[0].meta["gt_missing_frames"] == 0
    assert same_runs(back, expected)


def test_the_study_file_has_its_encodings(logdir, tmp_path):
    out = tmp_path / "s.parquet"
    parquet.ingest(logdir[0], out, on_error="quarantine", workers=1, progress=False)
    meta = pq.ParquetFile(out).metadata.row_group(0)
    columns = {meta.column(k).path_in_schema: meta.column(k) for k in range(meta.num_columns)}
    assert {c.compression for c in columns.values()} <= {"LZ4", "LZ4_RAW"}
    assert "BYTE_STREAM_SPLIT" in columns["vis_px"].encodings
    assert (
        "RLE_DICTIONARY" in columns["n_inliers"].encodings and "RLE_DICTIONARY" in columns["run_id"].encodings
    )
