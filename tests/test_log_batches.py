"""jsve.io._log_batches: many logs parsed as one give, log by log, what reading each alone gives (the
table bit for bit, or the same error), whatever mix of good and broken logs a batch holds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from logfactory import edit_line, make_run, read_lines, set_field, v1_text, write_lines

from jsve.io import _log_batches as batches
from jsve.io import _logs as logs
from jsve.io._errors import LogFormatError

N = 25


def _alone(path: Path):
    try:
        return logs.parse_table(path.read_bytes(), str(path))
    except LogFormatError as e:
        return e


def _same(batch, alone) -> bool:
    """The same error (type and message), or the same metadata, version and bit-identical columns."""
    if isinstance(alone, LogFormatError) or isinstance(batch, LogFormatError):
        return type(batch) is type(alone) and str(batch) == str(alone)
    (meta_b, version_b, table_b), (meta_a, version_a, table_a) = batch, alone
    if meta_b != meta_a or version_b != version_a or table_b.column_names != table_a.column_names:
        return False
    return all(
        table_b.column(c).type == table_a.column(c).type
        and np.array_equal(table_b.column(c).is_null().to_numpy(), table_a.column(c).is_null().to_numpy())
        and np.array_equal(
            table_b.column(c).fill_null(0).to_numpy().view(np.int64),
            table_a.column(c).fill_null(0).to_numpy().view(np.int64),
        )
        for c in table_a.column_names
    )


def _good(root: Path, k: int, **kwargs) -> Path:
    return logs.write_log(make_run(N, k, **kwargs), root / f"r{k:02d}.csv")


@pytest.fixture
def read_alone(monkeypatch) -> list[str]:
    """The logs that parse_logs hands to reading alone, in call order."""
    names: list[str] = []
    original = batches._alone

    def spy(source, data):
        names.append(Path(source).name)
        return original(source, data)

    monkeypatch.setattr(batches, "_alone", spy)
    return names


def _check(paths: list[Path]) -> list:
    items = [(str(p), p.read_bytes()) for p in paths]
    out = batches.parse_logs(items)
    for p, result in zip(paths, out, strict=True):
        assert _same(result, _alone(p)), (p, result)
    return out


def test_good_logs_of_one_sequence_parse_as_one_group(tmp_path, read_alone):
    # The same stamps in every log: stamps restart at each log's first row, which is no defect.
    paths = [_good(tmp_path, k, sequence="MH_01", t0_ns=1_000_000_000) for k in range(6)]
    out = _check(paths)
    assert all(not isinstance(r, LogFormatError) for r in out)
    assert read_alone == []  # the batch vouched for every log


def test_a_mixed_batch_gives_each_log_what_reading_it_alone_gives(tmp_path, read_alone):
    paths = [
        _good(tmp_path, 0),
        _good(tmp_path, 1, with_gt=False),  # another header: its own group
        _good(tmp_path, 2, no_pose=0.3, gt_missing=0.2),  # empty vis_* and gt_* fields
        _good(tmp_path, 3),
        _good(tmp_path, 4),
        _good(tmp_path, 5),
        _good(tmp_path, 6),
        _good(tmp_path, 7, awkward_floats=True),
    ]
    v1_text(_good(tmp_path, 8))  # format v1: its own group
    paths.append(tmp_path / "r08.csv")
    set_field(paths[3], 9, "imu_dt", "-0.05")  # a value rule: its whole group is read alone
    crlf = paths[4]
    crlf.write_bytes(crlf.read_bytes().replace(b"\n", b"\r\n"))  # Windows line ends: read alone
    lines = read_lines(paths[5])
    lines.insert(6, "")  # a blank line
    write_lines(paths[5], lines)
    edit_line(paths[6], 10, None)  # a row fewer than the end marker says
    out = _check(paths)
    errors = [isinstance(r, LogFormatError) for r in out]
    assert errors == [False, False, False, True, False, True, True, False, False]
    # Alone: the three with line-level defects, the CRLF log, and the value rule's whole group (gt_*
    # header); the groups without gt_* and of format v1 were vouched for.
    assert sorted(read_alone) == [f"r{k:02d}.csv" for k in (0, 2, 3, 4, 5, 6, 7)]


@pytest.mark.parametrize(
    ("column", "value"),
    [
        ("imu_dt", "0.05"),  # the first-frame rule, at the second log's first row
        ("imu_dqw", "0.5"),
        ("t_ns", "1"),  # stamps out of order inside the second log (line 3 is its first row)
    ],
)
def test_a_rule_broken_at_a_later_logs_first_rows_is_found(tmp_path, column, value):
    paths = [_good(tmp_path, k, sequence="MH_01") for k in range(3)]
    set_field(paths[1], 3 if column != "t_ns" else 4, column, value)
    out = _check(paths)
    assert [isinstance(r, LogFormatError) for r in out] == [False, True, False]


def test_broken_layouts_and_hexadecimal_numbers_are_read_alone(tmp_path):
    paths = [_good(tmp_path, k) for k in range(4)]
    edit_line(paths[0], len(read_lines(paths[0])), None)  # no end marker
    set_field(paths[1], 5, "n_inliers", "0x10")  # Arrow would read 16
    edit_line(paths[2], 2, "")  # no header
    out = _check(paths)
    assert [isinstance(r, LogFormatError) for r in out] == [True, True, True, False]


def test_iter_parsed_reads_every_path_in_order_and_stops_at_the_first_error(tmp_path, monkeypatch):
    monkeypatch.setattr(batches, "_BATCH_BYTES", 20_000)  # a few logs per batch
    paths = [_good(tmp_path, k) for k in range(12)]
    set_field(paths[7], 9, "imu_dt", "-0.05")
    names = [str(p) for p in paths] + [str(tmp_path / "missing.csv"), str(tmp_path / "x.csv.partial")]
    seen = []
    got = list(batches.iter_parsed(names, threads=2, on_batch=seen.append))
    assert [p for p, _ in got] == names and sum(seen) == len(names) and len(seen) > 2
    assert [k for k, (_, r) in enumerate(got) if isinstance(r, LogFormatError)] == [7, 12, 13]
    assert "cannot read the file" in str(got[12][1]) and "incomplete" in str(got[13][1])
    stopped = list(batches.iter_parsed(names, threads=2, stop_on_error=True))
    assert len(stopped) == 8 and isinstance(stopped[-1][1], LogFormatError)
