"""The domain errors of jsve's file readers: one exception type naming file, line, column and value for
jsve's own formats, one naming the file for trajectory files read through evo."""

from __future__ import annotations

import os

MAX_SHOWN = 80
"""Characters of an offending value shown in a message; longer values are cut with '...'."""


def shorten(text: str) -> str:
    """`text` cut to MAX_SHOWN characters for an error message."""
    return text if len(text) <= MAX_SHOWN else text[: MAX_SHOWN - 3] + "..."


def located(
    path: str,
    line: int | None,
    reason: str,
    column: str | None = None,
    value: str | None = None,
    what: str = "column",
    frame: int | None = None,
) -> str:
    """The message of a defect at a place in a file: `path:line: column 'name' = 'value': reason`,
    leaving out the parts that are None (`path: frame 12: ...` for runs in memory)."""
    loc = path
    if line is not None:
        loc = f"{loc}:{line}"
    elif frame is not None:
        loc = f"{loc}: frame {frame}"
    if column is None:
        return f"{loc}: {reason}"
    if value is None:
        return f"{loc}: {what} '{column}': {reason}"
    return f"{loc}: {what} '{column}' = '{shorten(value)}': {reason}"


class LogFormatError(ValueError):
    """A tracking log (or jsve Parquet file) that does not follow its format (v2, or v1 when it says v1).

    The message reads `path:line: column 'name' = 'value': reason`; parts that do not apply are left
    out (`path: reason` when the problem has no line, e.g. a `.partial` file).

    Attributes:
        path: the file, as given to the reader.
        line: 1-based line number in the file, or None (in-memory runs report `frame` instead).
        column: the column (or metadata key, or column range such as 'vis_qw..vis_qz'), or None.
        value: the offending value as written in the file, or None.
        reason: what is wrong, in words.
        frame: 0-based frame index, for runs validated in memory (`validate_run`, `write_log`).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        line: int | None,
        reason: str,
        *,
        column: str | None = None,
        value: str | None = None,
        what: str = "column",
        frame: int | None = None,
    ):
        self.path = os.fspath(path)
        self.line = line
        self.reason = reason
        self.column = column
        self.value = value
        self.what = what
        self.frame = frame
        super().__init__(self._message())

    def _message(self) -> str:
        return located(self.path, self.line, self.reason, self.column, self.value, self.what, self.frame)

    def __reduce__(self):
        # Exceptions pickle through self.args by default, which does not fit this signature; worker
        # processes send these back to the parent.
        kwargs = dict(column=self.column, value=self.value, what=self.what, frame=self.frame)
        return (_rebuild_error, (type(self), self.path, self.line, self.reason, kwargs))


class LogIncompleteError(LogFormatError):
    """A log whose writer did not finish: no end marker, a frame count that disagrees with the rows,
    an empty file, or a `.partial` file. The message always says that the log is incomplete."""


class LogVersionWarning(UserWarning):
    """A log (or jsve Parquet file) of an older format version was read, with documented defaults for
    what that version does not record (format v1: map_id = 0, imu_ba2 from the map's age; see
    jsve.io._schema.v1_defaults). The message names the file(s) and the defaults used."""


def _rebuild_error(cls, path, line, reason, kwargs):
    return cls(path, line, reason, **kwargs)


class TrajectoryFileError(ValueError):
    """A trajectory file (TUM, EuRoC, KITTI) that cannot be read, or an estimate that cannot be matched
    with its reference. Where evo reads a file it reports no line: the message names the file(s) and the
    cause (`cannot read est.txt as kitti: ...`, `b.tum holds no poses`); a value jsve refuses (NaN, a
    zero quaternion) is named as in LogFormatError: `est.txt:12: columns 'qx..qw' = '0 0 0 0': ...`
    (see `at`)."""

    @classmethod
    def at(
        cls,
        path: str | os.PathLike,
        line: int | None,
        reason: str,
        column: str,
        value: str,
        what: str = "column",
    ) -> TrajectoryFileError:
        """The error of a value at a line of a file, in LogFormatError's words."""
        return cls(located(os.fspath(path), line, reason, column, value, what))
