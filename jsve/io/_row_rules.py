"""The value rules of a log's frames (docs/log-format.md, "Rules"), vectorised: a table of small checks.

    find_problem(cols, gt_missing, vis_missing, starts)   the first violation, or None
    RULES                                                 the checks, each (Rows) -> None

Every check reads the frames' columns through `Rows` and appends the first violation it finds to
`Rows.found`; `find_problem` reports the first of all (lowest row, then leftmost column). The reader
and the in-memory validator (jsve.io._logs) share them, and turn the problem into a LogFormatError
naming the file, line (or frame), column and value.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from jsve.io import _schema as schema

_VIS_SET = frozenset(schema.VIS_COLUMNS)
_POSED = ", ".join(f"{s} ({schema.STATE_NAMES[s]})" for s in schema.POSED_STATES[:-1]) + (
    f" and {schema.POSED_STATES[-1]} ({schema.STATE_NAMES[schema.POSED_STATES[-1]]})"
)
_TOO_LARGE = (
    f"beyond float32's range (|x| <= {schema.FLOAT_MAX:.8g}), the range jsve computes in: "
    "no real metre, second or m/s is this large"
)


@dataclass
class Problem:
    """The first defect found in the frames; turned into a LogFormatError by the caller."""

    row: int  # 0-based frame
    order: int  # column position used to pick the first defect of a row
    column: str
    reason: str  # may contain '{ref}', replaced by 'line N' or 'frame N' of ref_row
    value_cols: tuple[str, ...] = ()  # columns whose values make up the value shown
    value: str | None = None  # explicit value, when it is not a field of the row
    what: str = "column"
    ref_row: int | None = None


@dataclass
class Rows:
    """The frames under check and the violations found so far.

    Checks go column by column (no [frames, k] copies): many logs are validated at once
    (rows_are_valid), and a pass per rule over every column at once would cost more than the parse.

    Attributes:
        cols: column name -> values [frames], in file order; ints int64, floats float64, gt_* and vis_*
            NaN where missing.
        gt_missing, vis_missing: bool [frames, 7] / [frames, 10] where a value is absent, or None.
        starts: the first row of each run.
        pos: column name -> position in the file (the order problems of one row are reported in).
    """

    cols: Mapping[str, np.ndarray]
    gt_missing: np.ndarray | None
    vis_missing: np.ndarray | None
    starts: np.ndarray
    pos: dict[str, int] = field(init=False)
    found: list[Problem] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.pos = {c: i for i, c in enumerate(self.cols)}

    @property
    def n_frames(self) -> int:
        return len(self.cols["t_ns"])

    def add(self, row: int, column: str, reason: str, value_cols: tuple[str, ...] = (), **kwargs) -> None:
        """A problem at (row, column), ordered by `order=` (default the column's position)."""
        order = kwargs.pop("order", None)
        self.found.append(
            Problem(row, self.pos[column] if order is None else order, column, reason, value_cols, **kwargs)
        )

    @staticmethod
    def first_cell(bads: np.ndarray | Sequence[np.ndarray | None]) -> tuple[int, int] | None:
        """(row, k) of the first True over the columns bads[k] (lowest row, then lowest k), or None;
        a None column has no True. An array is one column [frames] or columns [frames, k]."""
        if isinstance(bads, np.ndarray):
            bads = [bads] if bads.ndim == 1 else list(bads.T)
        best = None
        for k, bad in enumerate(bads):
            if bad is not None and bad.any():
                r = int(np.argmax(bad))
                if best is None or r < best[0]:
                    best = (r, k)
        return best

    def per_cell(self, bads, names: Sequence[str], reason: str | Callable[[int], str]) -> None:
        """One-field rule: bads[k] flags column names[k]; reason is a string, or a function of the row."""
        hit = self.first_cell(bads)
        if hit is not None:
            r, k = hit
            c = names[k]
            self.add(r, c, reason(r) if callable(reason) else reason, (c,))

    def outside(self, names: Sequence[str], low: float | None, high: float | None) -> list[np.ndarray | None]:
        """Per column, where a value is < low or > high (None: none is, from its min and max)."""
        out: list[np.ndarray | None] = []
        for c in names:
            x = self.cols[c]
            below = low is not None and x.min() < low
            above = high is not None and x.max() > high
            if not (below or above):
                out.append(None)
                continue
            bad = np.zeros(len(x), bool)
            if below:
                bad |= x < low
            if above:
                bad |= x > high
            out.append(bad)
        return out

    def finite_in_range(self, names: Sequence[str], missing: np.ndarray | None, no_value: str) -> None:
        """NaN / inf (an absent value, where `missing` says, is not NaN) and finite values float32, which
        jsve computes in, cannot hold."""
        not_finite: list[np.ndarray | None] = []
        huge: list[np.ndarray | None] = []
        for k, c in enumerate(names):
            x = self.cols[c]
            finite = np.isfinite(x)
            all_finite = finite.all()
            bad = None if all_finite else ~finite if missing is None else ~finite & ~missing[:, k]
            not_finite.append(bad)
            if all_finite:
                large = x.max() > schema.FLOAT_MAX or x.min() < -schema.FLOAT_MAX
            else:
                with np.errstate(invalid="ignore"):
                    large = bool(np.any(np.abs(x[finite]) > schema.FLOAT_MAX))
            if large:
                with np.errstate(invalid="ignore"):
                    huge.append((np.abs(x) > schema.FLOAT_MAX) & finite)
            else:
                huge.append(None)
        self.per_cell(not_finite, names, "NaN or inf is not allowed" + no_value)
        self.per_cell(huge, names, _TOO_LARGE)


# --------------------------------------------------------------------------------------------------
# The checks, in the order they are reported for equal rows


def finite_values(rows: Rows) -> None:
    """Floats finite and within float32's range (empty gt_* / vis_* fields are absent values)."""
    other = [c for c in schema.FLOAT_COLUMNS if c not in _VIS_SET] + [
        c for c in schema.WORLD_COLUMNS if c in rows.pos
    ]
    rows.finite_in_range(other, None, "")
    hint = " (leave all ten vis_* fields empty for a frame without a pose)"
    rows.finite_in_range(schema.VIS_COLUMNS, rows.vis_missing, hint if rows.vis_missing is not None else "")


def vis_all_or_none(rows: Rows) -> None:
    """A frame has all ten vis_* values or none, and none only outside schema.POSED_STATES."""
    if rows.vis_missing is None:
        return
    n_vis = len(schema.VIS_COLUMNS)
    n_missing = rows.vis_missing.sum(axis=1)
    partial = (n_missing > 0) & (n_missing < n_vis)
    hit = rows.first_cell(rows.vis_missing & partial[:, None])
    if hit is not None:
        r, k = hit
        c = schema.VIS_COLUMNS[k]
        present = n_vis - int(n_missing[r])
        # After the single-field rules of the row: a 'nan' written beside empty fields is reported as itself.
        rows.add(
            r,
            c,
            f"missing while {present} other vis_* values of this frame are present (a frame has "
            "all ten vis_* values, or none when the front-end has no pose)",
            (c,),
            order=rows.pos[schema.VIS_COLUMNS[-1]],
        )
    state = rows.cols["state"]
    hit = rows.first_cell((n_missing == n_vis) & np.isin(state, schema.POSED_STATES))
    if hit is not None:
        r, s = hit[0], int(state[hit[0]])
        c = schema.VIS_COLUMNS[0]
        rows.add(
            r,
            c,
            f"no pose in state {s} ({schema.STATE_NAMES[s]}): frames in states {_POSED} have one "
            "(vis_* may be empty only in the other states)",
            (c,),
        )


def ground_truth_all_or_none(rows: Rows) -> None:
    """gt_* finite where present, and all seven present or none."""
    if rows.gt_missing is None:
        return
    hint = " (leave all seven gt_* fields empty for a frame without ground truth)"
    rows.finite_in_range(schema.GT_COLUMNS, rows.gt_missing, hint)
    n_missing = rows.gt_missing.sum(axis=1)
    partial = (n_missing > 0) & (n_missing < len(schema.GT_COLUMNS))
    hit = rows.first_cell(rows.gt_missing & partial[:, None])
    if hit is not None:
        r, k = hit
        present = len(schema.GT_COLUMNS) - int(n_missing[r])
        rows.add(
            r,
            schema.GT_COLUMNS[k],
            f"missing while {present} other gt_* values of this frame are "
            "present (a frame has all seven gt_* values or none)",
            value="",
        )


def increasing_stamps(rows: Rows) -> None:
    """t_ns strictly increasing within each run."""
    t = rows.cols["t_ns"]
    if len(t) < 2:
        return
    bad = np.diff(t) <= 0
    bad[rows.starts[1:] - 1] = False  # from one run's last frame to the next run's first
    if not bad.any():
        return
    r = int(np.argmax(bad)) + 1
    if t[r] == t[r - 1]:
        reason = "duplicate timestamp: the same as {ref} (t_ns must be strictly increasing)"
    else:
        reason = (
            f"t_ns must be strictly increasing: {int(t[r - 1]) - int(t[r])} ns earlier than {{ref}} "
            f"({int(t[r - 1])}; rows unsorted)"
        )
    rows.add(r, "t_ns", reason, ("t_ns",), ref_row=r - 1)


def states_and_flags(rows: Rows) -> None:
    """state an eTrackingState; imu_init, imu_ba2 0 or 1; map_id >= 0; BA2 only after IMU init."""
    cols = rows.cols
    states = ", ".join(map(str, schema.VALID_STATES))
    rows.per_cell(
        ~np.isin(cols["state"], schema.VALID_STATES),
        ("state",),
        f"must be one of {states} (ORB-SLAM3 eTrackingState)",
    )
    imu_init = cols["imu_init"]
    rows.per_cell((imu_init != 0) & (imu_init != 1), ("imu_init",), "must be 0 or 1")
    if "map_id" not in cols:  # format v1
        return
    rows.per_cell(cols["map_id"] < 0, ("map_id",), "must be >= 0 (ORB-SLAM3 Map::GetId(), an unsigned id)")
    ba2 = cols["imu_ba2"]
    rows.per_cell((ba2 != 0) & (ba2 != 1), ("imu_ba2",), "must be 0 or 1")
    rows.per_cell(
        (ba2 == 1) & (imu_init == 0),
        ("imu_ba2",),
        "requires imu_init = 1 (ORB-SLAM3 runs inertial BA2 only on a map whose IMU is initialised)",
    )


def counts_in_range(rows: Rows) -> None:
    """Counts and bins >= 0, within int32 and uint16; n_inliers <= n_extracted; the bins' sum too."""
    count_names = schema.COUNT_COLUMNS + schema.BIN_COLUMNS
    rows.per_cell(rows.outside(count_names, 0, None), count_names, "must be >= 0 (a count)")
    rows.per_cell(
        rows.outside(schema.COUNT_COLUMNS, None, schema.COUNT_MAX),
        schema.COUNT_COLUMNS,
        f"must be <= {schema.COUNT_MAX} (ORB-SLAM3 counts in int; jsve holds counts as int32)",
    )
    rows.per_cell(
        rows.outside(schema.BIN_COLUMNS, None, schema.BIN_MAX),
        schema.BIN_COLUMNS,
        f"must be <= {schema.BIN_MAX} (keypoints of one SVE bin; jsve holds bins as uint16)",
    )
    n_ext, n_inl = rows.cols["n_extracted"], rows.cols["n_inliers"]
    rows.per_cell([n_inl > n_ext], ("n_inliers",), lambda r: f"must be <= n_extracted ({int(n_ext[r])})")
    # Clipped so that the sum cannot wrap around int64: a bin out of [0, BIN_MAX] is reported above.
    bin_sum = np.zeros(rows.n_frames, np.int64)
    for c, out_of_range in zip(
        schema.BIN_COLUMNS, rows.outside(schema.BIN_COLUMNS, 0, schema.BIN_MAX), strict=True
    ):
        bin_sum += rows.cols[c] if out_of_range is None else np.clip(rows.cols[c], 0, schema.BIN_MAX + 1)
    hit = rows.first_cell([bin_sum > n_ext])
    if hit is not None:  # reported after the row's single-field rules
        r = hit[0]
        rows.add(
            r,
            f"{schema.BIN_COLUMNS[0]}..{schema.BIN_COLUMNS[-1]}",
            f"the binned keypoints (sum {int(bin_sum[r])}) must not exceed n_extracted ({int(n_ext[r])})",
            value=str(int(bin_sum[r])),
            what="columns",
            order=rows.pos[schema.BIN_COLUMNS[-1]],
        )


def keyframe_columns(rows: Rows) -> None:
    """v3's keyframe columns (schema.KEYFRAME_COLUMNS): known event bits, traj 0/1 and only with a
    reference keyframe, ref_kf >= -1, rel_* all present and finite exactly where ref_kf >= 0."""
    if "ref_kf" not in rows.pos:
        return
    cols = rows.cols
    events, traj, ref = cols["events"], cols["traj"], cols["ref_kf"]
    rows.per_cell(
        (events < 0) | ((events & ~schema.EVENT_MASK) != 0),
        ("events",),
        f"must be a bit set of the known events (0..{schema.EVENT_MASK}; schema.EVENTS)",
    )
    rows.per_cell((traj != 0) & (traj != 1), ("traj",), "must be 0 or 1")
    rows.per_cell(ref < -1, ("ref_kf",), "must be >= -1 (a keyframe id, or -1 for none)")
    rows.per_cell((traj == 1) & (ref < 0), ("traj",), "is 1 without a reference keyframe (ref_kf -1)")
    rel = np.stack([cols[c] for c in schema.REL_COLUMNS], axis=1)
    has_ref = ref >= 0
    bad = (has_ref[:, None] & ~np.isfinite(rel)) | (~has_ref[:, None] & ~np.isnan(rel))
    hit = np.flatnonzero(bad.any(axis=1))
    if len(hit):
        r = int(hit[0])
        c = schema.REL_COLUMNS[int(np.argmax(bad[r]))]
        reason = (
            "must be a finite number where ref_kf >= 0"
            if has_ref[r]
            else "must be empty where ref_kf is -1 (no reference keyframe)"
        )
        rows.add(r, c, reason, (c,))


def unit_quaternions(rows: Rows) -> None:
    """Every quaternion group of unit norm (schema.UNIT_QUATERNION_TOLERANCE)."""
    tol = schema.UNIT_QUATERNION_TOLERANCE
    for names in schema.QUATERNION_GROUPS.values():
        if names[0] not in rows.pos:
            continue
        norm = np.sqrt(sum(rows.cols[c] * rows.cols[c] for c in names))
        # NaN rows compare False: reported above, or a frame without ground truth or without a pose.
        hit = rows.first_cell(np.abs(norm - 1.0) > tol)
        if hit is not None:
            r = hit[0]
            rows.add(
                r,
                f"{names[0]}..{names[-1]}",
                f"not a unit quaternion: |q| = {norm[r]:.12g} (tolerance {tol:g})",
                tuple(names),
                what="columns",
                order=rows.pos[names[-1]],
            )


def imu_and_world(rows: Rows) -> None:
    """imu_dt >= 0; the world similarity's scale > 0."""
    rows.per_cell(rows.cols["imu_dt"] < 0, ("imu_dt",), "must be >= 0 (seconds since the previous frame)")
    if schema.WORLD_SCALE in rows.pos:
        rows.per_cell(
            ~(rows.cols[schema.WORLD_SCALE] > 0),
            (schema.WORLD_SCALE,),
            "must be > 0 (the scale of the similarity between world frames)",
        )


def first_frames(rows: Rows) -> None:
    """A run's first frame has nothing to preintegrate from (docs/log-format.md, "First frame")."""
    if not rows.n_frames:
        return
    starts, cols = rows.starts, rows.cols
    first_reason = "must be {} on the first frame (no previous frame to preintegrate from)"
    for c in ("imu_dt",) + schema.IMU_DP + schema.IMU_DV:
        bad = cols[c][starts] != 0.0
        if bad.any():
            rows.add(int(starts[np.argmax(bad)]), c, first_reason.format(0), (c,))
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    bad = (np.stack([cols[c][starts] for c in schema.IMU_DQ], axis=1) != identity).any(axis=1)
    if bad.any():
        rows.add(
            int(starts[np.argmax(bad)]),
            f"{schema.IMU_DQ[0]}..{schema.IMU_DQ[-1]}",
            first_reason.format("the identity (1, 0, 0, 0)"),
            schema.IMU_DQ,
            what="columns",
            order=rows.pos[schema.IMU_DQ[-1]],
        )


RULES: tuple[Callable[[Rows], None], ...] = (
    finite_values,
    vis_all_or_none,
    ground_truth_all_or_none,
    increasing_stamps,
    states_and_flags,
    counts_in_range,
    keyframe_columns,
    unit_quaternions,
    imu_and_world,
    first_frames,
)
"""Every value rule, in the order problems of equal rank are reported."""


def find_problem(
    cols: Mapping[str, np.ndarray],
    gt_missing: np.ndarray | None,
    vis_missing: np.ndarray | None,
    starts: np.ndarray | None = None,
) -> Problem | None:
    """First (lowest row, then leftmost column) violation of the value rules, or None.

    Arguments:
        cols: column name -> values [frames], in file order (v2, or v1 without map_id / imu_ba2);
            ints int64, floats float64, gt_* and vis_* NaN where missing.
        gt_missing: bool [frames, 7], True where a gt value is absent (an empty field in a file; NaN in
            memory), or None when there are no gt columns.
        vis_missing: bool [frames, 10], True where a vis_* value is absent (as gt_missing), or None
            where no vis_* value may be absent (format v1).
        starts: the first row of each run, for several runs' rows checked at once (rows_are_valid):
            stamps then increase within each run and the first-frame rules hold at each start. Default
            one run.
    """
    n_frames = len(cols["t_ns"])
    starts = np.zeros(1 if n_frames else 0, np.int64) if starts is None else np.asarray(starts)
    rows = Rows(cols, gt_missing, vis_missing, starts)
    for rule in RULES:
        rule(rows)
    return min(rows.found, key=lambda p: (p.row, p.order)) if rows.found else None


__all__ = ["Problem", "Rows", "RULES", "find_problem"]
