"""jsve.io._errors: messages name file, line, column and value; errors survive pickling (worker processes)."""

from __future__ import annotations

import pickle
import warnings

import pytest
from logfactory import make_run, set_field, v1_text

from jsve.io import _logs as logs
from jsve.io._errors import (
    MAX_SHOWN,
    LogFormatError,
    LogIncompleteError,
    LogVersionWarning,
    TrajectoryFileError,
    shorten,
)


def test_message_names_what_applies():
    assert str(LogFormatError("r7.csv", 12, "must be >= 0", column="imu_dt", value="-0.05")) == (
        "r7.csv:12: column 'imu_dt' = '-0.05': must be >= 0"
    )
    assert (
        str(LogFormatError("r7.csv", 2, "wrong order", column="t_ns"))
        == "r7.csv:2: column 't_ns': wrong order"
    )
    assert str(LogFormatError("r7.csv", None, "no frames")) == "r7.csv: no frames"
    memory = LogFormatError("<memory>", None, "must be 0 or 1", column="imu_init", value="2", frame=4)
    assert str(memory) == "<memory>: frame 4: column 'imu_init' = '2': must be 0 or 1"


def test_long_values_are_shortened():
    assert shorten("x" * MAX_SHOWN) == "x" * MAX_SHOWN
    cut = shorten("x" * (MAX_SHOWN + 1))
    assert len(cut) == MAX_SHOWN and cut.endswith("...")
    err = LogFormatError("a.csv", 3, "not a number", column="x", value="9" * 200)
    assert f"'{'9' * (MAX_SHOWN - 3)}...'" in str(err)
    assert err.value == "9" * 200  # the attribute keeps the whole value


def test_errors_pickle_with_their_attributes(tmp_path):
    log = logs.write_log(make_run(20, seed=3), tmp_path / "r7.csv")
    set_field(log, 12, "imu_dt", "-0.05")
    with pytest.raises(LogFormatError) as info:
        logs.read_log(log)
    back = pickle.loads(pickle.dumps(info.value))
    assert type(back) is LogFormatError and str(back) == str(info.value)
    assert (back.path, back.line, back.column, back.value, back.reason) == (
        str(log),
        12,
        "imu_dt",
        "-0.05",
        info.value.reason,
    )
    inc = pickle.loads(pickle.dumps(LogIncompleteError("a.csv", 3, "the log is incomplete")))
    assert type(inc) is LogIncompleteError and inc.line == 3


def test_trajectory_errors_are_value_errors():
    # Callers that catch ValueError for unusable input (the CLI) catch it too.
    err = TrajectoryFileError("b.tum holds no poses")
    assert isinstance(err, ValueError) and str(err) == "b.tum holds no poses"


def test_v1_version_warning_is_a_user_warning_that_can_be_made_an_error(tmp_path):
    # Scripts that turn UserWarnings into errors stop on a v1 log; jsve never silently guesses.
    log = logs.write_log(make_run(20, seed=3), tmp_path / "r7.csv")
    v1_text(log)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        with pytest.raises(LogVersionWarning, match=r"r7\.csv: format v1 log read with defaults: map_id = 0"):
            logs.read_log(log)
    assert issubclass(LogVersionWarning, UserWarning) and not issubclass(LogVersionWarning, LogFormatError)
