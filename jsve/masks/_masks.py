"""Dynamic-object masks (Masked ORB-SLAM3): mask readers, Algorithm 1 in JAX, masked counts of a run.

Three layers (docs/masks.md describes them for people):

    MotsMasks(path)          KITTI MOTS instances_txt, parsed once into per-frame line offsets; masks
                             decoded with pycocotools on demand, one frame at a time
    PngMasks(folder)         one PNG per frame: binary masks, or KITTI MOTS instance PNGs with `classes`
    dynamic_keypoints(...)   Algorithm 1 for one frame (pure JAX; vmap it over frames)
    sve_bin_index(...)       ORB-SLAM3's grid cell -> SVE bin of every keypoint (pure JAX)
    frame_counts(...)        n_extracted, n_inliers and the 64 bins of the kept keypoints (pure JAX)
    apply_masks(run, keypoints, masks) / masked_log(...)
                             a run's counts and bins recomputed without the keypoints on dynamic
                             objects, from its keypoint side file (jsve.io._keypoints)

KITTI MOTS: a line is `frame obj_id class_id img_h img_w rle` with the mask as COCO compressed RLE
(column-major run lengths, LEB128-like characters 48..111); class_id = obj_id // 1000; classes 1 car,
2 pedestrian, 10 ignore region (obj_id 10000). Frames without objects have no line.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jsve.core._numerics import round_half_away
from jsve.io import _schema as schema
from jsve.io._keypoints import KeypointLog, check_matches_log, frame_of_keypoints
from jsve.io._logs import LogFormatError
from jsve.io._schema import RunLog

CAR = 1
PEDESTRIAN = 2
IGNORE = 10
"""KITTI MOTS class ids (obj_id // 1000); 10 marks an ignore region (obj_id 10000)."""

DYNAMIC_CLASSES: tuple[int, ...] = (CAR, PEDESTRIAN)
"""Classes whose pixels Masked ORB-SLAM3 treats as dynamic."""

GRID_COLS = 64
GRID_ROWS = 48
"""ORB-SLAM3's keypoint grid (FRAME_GRID_COLS x FRAME_GRID_ROWS); SVE bins it 8 x 8."""

MOTS_FIELDS = ("frame", "obj_id", "class_id", "img_height", "img_width", "rle")

_RLE_FIRST, _RLE_LAST = 48, 111  # '0' .. 'o': a character holds 6 bits (value + 48)
_RLE_MAX_CHARS = 12  # 12 characters carry 60 bits; more cannot be a count of a real image


# --------------------------------------------------------------------------------------------------
# COCO compressed RLE


def rle_counts(counts: bytes) -> np.ndarray:
    """The run lengths of a COCO compressed RLE string, validated.

    Format (pycocotools maskApi.c, rleToString / rleFrString): each run length is written in groups of
    5 bits, least significant first, one character (value + 48) per group; bit 0x20 of a group says
    another group follows, and bit 0x10 of the last group is a sign bit. From the fourth run on, the
    value stored is the difference to the run two places earlier (runs alternate 0s and 1s).

    Arguments:
        counts: the string as bytes.

    Returns:
        int64 [m] run lengths, alternating zeros and ones of the column-major mask, starting with zeros.

    Raises:
        ValueError: a character outside '0'..'o', a string that ends inside a run length, an over-long
            group, or a negative run length; the message says which and where.
    """
    c = np.frombuffer(counts, np.uint8).astype(np.int64)
    if c.size == 0:
        raise ValueError("empty RLE string")
    bad = (c < _RLE_FIRST) | (c > _RLE_LAST)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(
            f"{_describe_byte(int(c[k]))} at position {k} is not valid in a COCO compressed RLE "
            f"(characters '0'..'o', ASCII {_RLE_FIRST}-{_RLE_LAST})"
        )
    c -= _RLE_FIRST
    more = (c & 0x20) != 0
    if more[-1]:
        raise ValueError("the RLE string ends in the middle of a run length (continuation bit set)")
    group = np.concatenate([[0], np.cumsum(~more[:-1])])  # run-length index of every character
    starts = np.flatnonzero(np.concatenate([[True], ~more[:-1]]))
    position = np.arange(c.size) - starts[group]
    if position.max() >= _RLE_MAX_CHARS:
        raise ValueError(f"a run length spans more than {_RLE_MAX_CHARS} characters")
    values = np.zeros(starts.size, np.int64)
    np.add.at(values, group, (c & 0x1F) << (5 * position))
    ends = np.flatnonzero(~more)
    negative = (c[ends] & 0x10) != 0
    values -= np.where(negative, np.left_shift(1, 5 * (position[ends] + 1)), 0)  # sign extension
    runs = values.copy()
    runs[2::2] = np.cumsum(values[2::2])  # runs i > 2 are stored as differences to run i - 2
    runs[1::2] = np.cumsum(values[1::2])
    if (runs < 0).any():
        k = int(np.argmax(runs < 0))
        raise ValueError(f"run length {k} is negative ({int(runs[k])})")
    return runs


def _describe_byte(b: int) -> str:
    return f"character {chr(b)!r}" if 32 <= b < 127 else f"byte 0x{b:02x}"


# --------------------------------------------------------------------------------------------------
# Mask sources


class MaskSource(Protocol):
    """What `apply_masks` needs: the mask size and one boolean mask per key (frame index or stamp)."""

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of every mask, px."""

    def mask(self, key: int) -> np.ndarray:
        """bool [height, width], True on dynamic pixels."""


@dataclass(frozen=True)
class MotsInstance:
    """One line of a KITTI MOTS instances_txt file (the mask itself stays in the file until decoded).

    Attributes:
        frame: image index in the sequence.
        obj_id: object id, class_id * 1000 + instance (10000 for an ignore region).
        class_id: 1 car, 2 pedestrian, 10 ignore region.
        line: 1-based line in the file.
        offset, length: bytes of the RLE field in the file.
    """

    frame: int
    obj_id: int
    class_id: int
    line: int
    offset: int
    length: int


class MotsMasks:
    """KITTI MOTS instances_txt annotations as per-frame binary masks, decoded lazily.

    The file is read once on construction: every line's fields are checked (integers, sizes, class ids,
    the RLE string's structure and that its runs cover exactly img_h x img_w pixels) and its byte offset
    is kept per frame. A mask is decoded (pycocotools) only when asked for, so a long sequence never
    sits in memory; `iter_masks` walks the frames one at a time.

    Arguments:
        path: the instances_txt file (e.g. `instances_txt/0000.txt`).
        classes: class ids whose instances `mask` unites (default car and pedestrian). Ignore regions
            (10) are kept apart in `ignore_mask`; put 10 in `classes` to include them.

    Raises:
        LogFormatError: `path:line: field 'name' = 'value': reason` for the first malformed line.
        OSError: the file cannot be read.
    """

    def __init__(self, path: str | os.PathLike, classes: Sequence[int] = DYNAMIC_CLASSES):
        self.path = os.fspath(path)
        self.classes = _check_classes(classes)
        with open(self.path, "rb") as f:
            data = f.read()
        self._by_frame: dict[int, list[MotsInstance]] = {}
        size = None
        offset = 0
        for line_no, raw in enumerate(data.split(b"\n"), start=1):
            start, offset = offset, offset + len(raw) + 1
            if offset > len(data) and not raw:
                break  # the file ends with a newline
            instance, shape = self._parse_line(raw.rstrip(b"\r"), line_no, start, size)
            size = size or shape
            seen = self._by_frame.setdefault(instance.frame, [])
            twin = next((i for i in seen if i.obj_id == instance.obj_id), None)
            if twin is not None:
                self._fail(
                    line_no,
                    "obj_id",
                    str(instance.obj_id),
                    f"repeats line {twin.line} in frame {instance.frame}",
                )
            seen.append(instance)
        if size is None:
            raise LogFormatError(self.path, None, "no annotation lines: the image size is unknown")
        self._shape = size

    def _fail(self, line: int, field: str | None, value: str | None, reason: str):
        raise LogFormatError(self.path, line, reason, column=field, value=value, what="field")

    def _parse_line(self, raw: bytes, line: int, start: int, size):
        # Fields stay bytes until checked, so that the RLE's offset and length are those in the file.
        parts = raw.split(b" ")
        fields = [p.decode("ascii", errors="replace") for p in parts]
        text = raw.decode("ascii", errors="replace")
        if len(fields) != len(MOTS_FIELDS) or not all(fields):
            self._fail(
                line,
                None,
                None,
                f"expected {len(MOTS_FIELDS)} space-separated fields ({' '.join(MOTS_FIELDS)}), "
                f"found {len([f for f in fields if f])}" + (" (an empty line)" if not text.strip() else ""),
            )
        numbers = []
        for name, field in zip(MOTS_FIELDS[:5], fields[:5], strict=True):
            if not re.fullmatch(r"[0-9]+", field):
                self._fail(line, name, field, "not a non-negative integer")
            numbers.append(int(field))
        frame, obj_id, class_id, height, width = numbers
        if height == 0 or width == 0:
            self._fail(line, "img_height" if height == 0 else "img_width", "0", "must be positive (pixels)")
        if class_id != obj_id // 1000:
            self._fail(
                line,
                "class_id",
                fields[2],
                f"object {obj_id} belongs to class {obj_id // 1000} (class_id = obj_id // 1000)",
            )
        if size is not None and (height, width) != size:
            self._fail(
                line,
                "img_height" if height != size[0] else "img_width",
                fields[3] if height != size[0] else fields[4],
                f"the image is {height} x {width} here but {size[0]} x {size[1]} on the first line",
            )
        rle = parts[5]
        try:
            runs = rle_counts(rle)
        except ValueError as e:
            self._fail(line, "rle", fields[5], str(e))
        if runs.sum() != height * width:
            self._fail(
                line,
                "rle",
                fields[5],
                f"the runs cover {int(runs.sum())} pixels but the image has "
                f"{height} x {width} = {height * width}",
            )
        rle_offset = start + len(raw) - len(rle)
        return MotsInstance(frame, obj_id, class_id, line, rle_offset, len(rle)), (height, width)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the images, px, from the file."""
        return self._shape

    @property
    def frames(self) -> list[int]:
        """The annotated frames (those with at least one line), sorted."""
        return sorted(self._by_frame)

    @property
    def n_frames(self) -> int:
        """Last annotated frame + 1: the frames `iter_masks` walks by default."""
        return max(self._by_frame) + 1

    def instances(self, frame: int) -> list[MotsInstance]:
        """The instances of a frame, in file order (empty for a frame without annotations)."""
        return list(self._by_frame.get(int(frame), ()))

    def rle(self, instance: MotsInstance) -> dict:
        """The pycocotools RLE object of an instance: {'size': [h, w], 'counts': bytes}."""
        return self._rles([instance])[0]

    def _rles(self, instances: Sequence[MotsInstance]) -> list[dict]:
        out = []
        with open(self.path, "rb") as f:
            for instance in instances:
                f.seek(instance.offset)
                out.append({"size": list(self._shape), "counts": f.read(instance.length)})
        return out

    def decode(self, instances: Sequence[MotsInstance]) -> np.ndarray:
        """Union of the instances' masks, bool [height, width] (all False for none)."""
        if not instances:
            return np.zeros(self._shape, bool)
        from pycocotools import mask as mask_util

        stack = mask_util.decode(self._rles(instances))  # [h, w, n] uint8, column-major
        return np.ascontiguousarray(stack.any(axis=2))

    def instance_mask(self, instance: MotsInstance) -> np.ndarray:
        """One instance's mask, bool [height, width]."""
        return self.decode([instance])

    def mask(self, frame: int) -> np.ndarray:
        """Union of the frame's instances of `classes`, bool [height, width]."""
        return self.decode([i for i in self.instances(frame) if i.class_id in self.classes])

    def ignore_mask(self, frame: int) -> np.ndarray:
        """Union of the frame's ignore regions (class 10), bool [height, width]."""
        return self.decode([i for i in self.instances(frame) if i.class_id == IGNORE])

    __getitem__ = mask

    def iter_masks(self, n_frames: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """(frame, mask) for frames 0 .. n_frames - 1 (default `self.n_frames`), decoded one at a time."""
        for frame in range(self.n_frames if n_frames is None else n_frames):
            yield frame, self.mask(frame)

    def __iter__(self) -> Iterator[np.ndarray]:
        return (m for _, m in self.iter_masks())

    def __len__(self) -> int:
        return self.n_frames

    def describe(self) -> str:
        """A one-line description for log metadata."""
        return f"kitti_mots:{self.path} classes={list(self.classes)}"


class PngMasks:
    """One mask PNG per frame in a folder, read on demand.

    The key of a file is the last run of digits in its name (`000042.png` -> 42, EuRoC's
    `1403636579763555584.png` -> the stamp), to be matched with frame indices or stamps (see
    `apply_masks(key=...)`).

    Arguments:
        folder: the folder (not searched recursively).
        classes: None: every non-zero pixel is set (binary masks; any channel of a colour image).
            A sequence of class ids: the image is a KITTI MOTS instance map (one 16-bit channel, pixel
            value obj_id = class_id * 1000 + instance, 10000 ignore, 0 background) and the pixels whose
            class is listed are set.
        missing: "error" (a key without a file raises) or "empty" (it has an empty mask).

    Raises:
        FileNotFoundError: no PNG in the folder. LogFormatError: two files with the same key, or an
        image of another size or that cannot be read (naming the file).
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        classes: Sequence[int] | None = None,
        missing: Literal["error", "empty"] = "error",
    ):
        if missing not in ("error", "empty"):
            raise ValueError(f"missing must be 'error' or 'empty', got {missing!r}")
        self.folder = Path(folder)
        self.classes = None if classes is None else _check_classes(classes)
        self.missing = missing
        self._files: dict[int, Path] = {}
        for path in sorted(self.folder.glob("*.png")):
            digits = re.findall(r"[0-9]+", path.stem)
            if not digits:
                continue
            key = int(digits[-1])
            if key in self._files:
                raise LogFormatError(
                    os.fspath(path), None, f"has the same frame number {key} as {self._files[key].name}"
                )
            self._files[key] = path
        if not self._files:
            raise FileNotFoundError(f"no numbered *.png masks in {os.fspath(self.folder)!r}")
        self._shape = self._read(self._files[min(self._files)], check_shape=False).shape

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), px, of the first mask."""
        return self._shape

    @property
    def keys(self) -> list[int]:
        """The frame numbers (or stamps) that have a file, sorted."""
        return sorted(self._files)

    def _read(self, path: Path, check_shape: bool = True) -> np.ndarray:
        import cv2

        image = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise LogFormatError(os.fspath(path), None, "cannot be read as an image")
        if self.classes is None:
            mask = image != 0 if image.ndim == 2 else (image != 0).any(axis=2)
        else:
            if image.ndim != 2:
                raise LogFormatError(
                    os.fspath(path),
                    None,
                    f"a KITTI MOTS instance map has one channel, this image has {image.shape[2]}",
                )
            mask = (image != 0) & np.isin(image.astype(np.int64) // 1000, self.classes)
        if check_shape and mask.shape != self._shape:
            raise LogFormatError(
                os.fspath(path),
                None,
                f"is {mask.shape[0]} x {mask.shape[1]} px, "
                f"the first mask {self._shape[0]} x {self._shape[1]}",
            )
        return mask

    def mask(self, key: int) -> np.ndarray:
        """The mask of frame number (or stamp) `key`, bool [height, width]."""
        path = self._files.get(int(key))
        if path is None:
            if self.missing == "empty":
                return np.zeros(self._shape, bool)
            raise FileNotFoundError(f"{os.fspath(self.folder)}: no mask PNG for frame {key}")
        return self._read(path)

    __getitem__ = mask

    def describe(self) -> str:
        classes = "nonzero" if self.classes is None else f"classes={list(self.classes)}"
        return f"png:{os.fspath(self.folder)} {classes}"


def _check_classes(classes) -> tuple[int, ...]:
    out = tuple(int(c) for c in classes)
    if not out or any(c <= 0 for c in out):
        raise ValueError(
            f"classes must be positive class ids (1 car, 2 pedestrian, 10 ignore), got {classes!r}"
        )
    return out


# --------------------------------------------------------------------------------------------------
# Algorithm 1 and the masked counts (pure JAX)


def dynamic_keypoints(
    mask: Bool[Array, "H W"], xy: Float[Array, "N 2"], valid: Bool[Array, " N"]
) -> Bool[Array, " N"]:
    """Algorithm 1 (Masked ORB-SLAM3): the keypoints that lie on a dynamic object.

    A keypoint (x, y) is dynamic when the mask is set at any of its four integer neighbours
    (floor x, floor y), (floor x + 1, floor y), (floor x, floor y + 1), (floor x + 1, floor y + 1),
    where x is the column and y the row. A neighbour outside the image counts as not set: nothing wraps
    around (a keypoint at x = -0.5 looks at columns -1, outside, and 0). Padded keypoints
    (valid = False) are never dynamic, whatever their coordinates.

    Arguments:
        mask: [H, W] bool, True on dynamic pixels (row y, column x).
        xy: [N, 2] keypoint positions (x, y), px, image coordinates as extracted.
        valid: [N] False on padding.

    Returns:
        [N] bool, True for keypoints to remove.
    """
    if mask.ndim != 2:
        raise ValueError(f"mask must have shape (H, W), got {tuple(mask.shape)}")
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"xy must have shape (N, 2), got {tuple(xy.shape)}")
    if valid.shape != xy.shape[:1]:
        raise ValueError(f"valid must have shape ({xy.shape[0]},) like xy, got {tuple(valid.shape)}")
    height, width = mask.shape
    # Clipping to [-2, size] keeps "outside" outside (both neighbours of -2 and of size are off the image)
    # and keeps huge or padded values from overflowing int32.
    fx = jnp.clip(jnp.floor(xy[:, 0]), -2, width).astype(jnp.int32)
    fy = jnp.clip(jnp.floor(xy[:, 1]), -2, height).astype(jnp.int32)
    mask = mask.astype(bool)

    def is_set(cx, cy):
        inside = (cx >= 0) & (cx < width) & (cy >= 0) & (cy < height)
        # Clamped indices only read a pixel that `inside` then discards: no negative-index wrap-around.
        return inside & mask[jnp.clip(cy, 0, height - 1), jnp.clip(cx, 0, width - 1)]

    hit = is_set(fx, fy) | is_set(fx + 1, fy) | is_set(fx, fy + 1) | is_set(fx + 1, fy + 1)
    return hit & valid.astype(bool)


def sve_bin_index(grid_xy: Float[Array, "*batch 2"], bounds: Float[ArrayLike, " 4"]) -> Int[Array, "*batch"]:
    """The SVE bin (0..63, row-major) of every keypoint, or -1 for a keypoint outside ORB-SLAM3's grid.

    ORB-SLAM3 v1.0 Frame::PosInGrid, in float32 as ORB-SLAM3 computes it: col = round((x - min_x) *
    (64 / (max_x - min_x))), row = round((y - min_y) * (48 / (max_y - min_y))), C rounding; a keypoint
    with col outside [0, 64) or row outside [0, 48) is in no cell. SVE bins the grid 8 x 8:
    bin = 8 (row // 6) + col // 8.

    Arguments:
        grid_xy: [..., 2] undistorted keypoint positions (ORB-SLAM3's mvKeysUn), px.
        bounds: [4] (min_x, max_x, min_y, max_y), px, the undistorted image bounds (Frame::ComputeImageBounds;
            (0, width, 0, height) for an image without distortion).

    Returns:
        [...] int32 bin index, -1 outside the grid.
    """
    if grid_xy.shape[-1:] != (2,):
        raise ValueError(f"grid_xy must have shape (..., 2), got {tuple(grid_xy.shape)}")
    if jnp.shape(bounds) != (4,):
        raise ValueError(f"bounds must be (min_x, max_x, min_y, max_y), got shape {jnp.shape(bounds)}")
    f32 = jnp.float32
    b = jnp.asarray(bounds).astype(f32)
    x = grid_xy[..., 0].astype(f32)
    y = grid_xy[..., 1].astype(f32)
    inv_w = f32(GRID_COLS) / (b[1] - b[0])  # mfGridElementWidthInv
    inv_h = f32(GRID_ROWS) / (b[3] - b[2])
    col = round_half_away((x - b[0]) * inv_w)
    row = round_half_away((y - b[2]) * inv_h)
    inside = (col >= 0) & (col < GRID_COLS) & (row >= 0) & (row < GRID_ROWS)
    col = jnp.where(inside, col, 0).astype(jnp.int32)
    row = jnp.where(inside, row, 0).astype(jnp.int32)
    per_x, per_y = GRID_COLS // 8, GRID_ROWS // 8
    return jnp.where(inside, (row // per_y) * 8 + col // per_x, -1)


def frame_counts(
    keep: Bool[Array, " N"], inlier: Bool[Array, " N"], bin_index: Int[Array, " N"]
) -> tuple[Int[Array, ""], Int[Array, ""], Int[Array, " 64"]]:
    """Counts of one frame over the kept keypoints: (n_extracted, n_inliers, bins [64]).

    Arguments:
        keep: [N] keypoints to count (False on padding and on removed keypoints).
        inlier: [N] map-point inliers after TrackLocalMap.
        bin_index: [N] SVE bin of each keypoint (`sve_bin_index`), -1 for none.
    """
    if keep.ndim != 1 or inlier.shape != keep.shape or bin_index.shape != keep.shape:
        raise ValueError(
            f"keep, inlier and bin_index must have one shape (N,), got {tuple(keep.shape)}, "
            f"{tuple(inlier.shape)} and {tuple(bin_index.shape)}"
        )
    keep = keep.astype(bool)
    n_extracted = jnp.sum(keep, dtype=jnp.int32)
    n_inliers = jnp.sum(keep & inlier.astype(bool), dtype=jnp.int32)
    target = jnp.where(keep & (bin_index >= 0), bin_index, schema.N_BINS)
    bins = jnp.zeros(schema.N_BINS, jnp.int32).at[target].add(1, mode="drop")
    return n_extracted, n_inliers, bins


@jax.jit
def _chunk_kernel(masks, ixy, grid_xy, inlier, valid, bounds):
    """Algorithm 1 and both sets of counts (all keypoints; kept keypoints) over a chunk of frames."""
    removed = jax.vmap(dynamic_keypoints)(masks, ixy, valid)
    bin_index = sve_bin_index(grid_xy, bounds)
    counts = jax.vmap(frame_counts)
    return removed, counts(valid, inlier, bin_index), counts(valid & ~removed, inlier, bin_index)


# --------------------------------------------------------------------------------------------------
# Applying masks to a run


@dataclass(frozen=True)
class MaskedRun:
    """A run with its dynamic keypoints removed.

    Attributes:
        log: the run with n_extracted, n_inliers and bin_0..bin_63 recomputed over the kept keypoints
            (every other column unchanged; metadata gains "masks", a description of the mask source).
        removed: [K] bool, per row of the keypoint side file: True where Algorithm 1 removed it.
        n_removed: [F] int64 keypoints removed per frame.
    """

    log: RunLog
    removed: np.ndarray
    n_removed: np.ndarray


def apply_masks(
    run: RunLog,
    keypoints: KeypointLog,
    masks: MaskSource,
    *,
    key: Literal["frame", "t_ns"] = "frame",
    verify: bool = True,
    verify_bins: bool = True,
    chunk_frames: int = 16,
) -> MaskedRun:
    """Remove the keypoints on dynamic objects from a run and recompute its counts and SVE bins.

    Frames are processed in chunks of `chunk_frames` (one compiled kernel, masks decoded chunk by chunk),
    so memory stays bounded however long the run is.

    Arguments:
        run: the tracking log.
        keypoints: its side file (same run id, every keypoint of every frame; see jsve.io._keypoints).
        masks: a mask source (MotsMasks, PngMasks, ...) of the run's image size.
        key: how a frame finds its mask: "frame" (its 0-based index, as KITTI numbers images) or "t_ns"
            (its stamp, as EuRoC names images).
        verify: check that the keypoints reproduce the log's n_extracted and n_inliers on every frame.
        verify_bins: check that they reproduce its bins too (needs the log's bins to come from
            ORB-SLAM3's grid over `image_bounds`, as jsve_log.hpp's fill_bins_from_grid does).
        chunk_frames: frames per kernel call.

    Returns:
        MaskedRun.

    Raises:
        LogFormatError: keypoints of another run, a keypoint stamp that is no frame, or (verify) a frame
            whose keypoints disagree with the log, naming the side file and line.
        ValueError: masks of another image size than the keypoints' image_size, or a bad argument.
    """
    if key not in ("frame", "t_ns"):
        raise ValueError(f"key must be 'frame' or 't_ns', got {key!r}")
    if chunk_frames < 1:
        raise ValueError(f"chunk_frames must be positive, got {chunk_frames}")
    check_matches_log(keypoints, run)
    width, height = keypoints.image_size
    if tuple(masks.shape) != (height, width):
        raise ValueError(
            f"masks are {masks.shape[0]} x {masks.shape[1]} px (height x width) but {keypoints.source} "
            f"has image_size [{width}, {height}]"
        )
    t_ns = run.frames["t_ns"].to_numpy()
    n_frames = len(t_ns)
    frame_of = frame_of_keypoints(keypoints, t_ns, run.source)
    kp = keypoints.keypoints
    n_kp = len(kp)
    per_frame = np.bincount(frame_of, minlength=n_frames)
    offsets = np.concatenate([[0], np.cumsum(per_frame)])
    width_n = max(128, -(-int(per_frame.max(initial=0)) // 128) * 128)  # one compiled shape per run
    slot = np.arange(n_kp) - offsets[frame_of]
    # Floors on the host in float64: the kernel may run in float32, where 2.9999999 would round to 3.
    ixy = np.floor(kp[["x", "y"]].to_numpy())
    grid_xy = kp[["ux", "uy"]].to_numpy(np.float32)  # ORB-SLAM3 keeps keypoints as floats
    inlier = kp["inlier"].to_numpy() == 1
    bounds = np.asarray(keypoints.image_bounds, np.float32)

    removed = np.zeros(n_kp, bool)
    full = np.zeros((n_frames, 2 + schema.N_BINS), np.int64)
    kept = np.zeros((n_frames, 2 + schema.N_BINS), np.int64)
    for start in range(0, n_frames, chunk_frames):
        stop = min(start + chunk_frames, n_frames)
        lo, hi = offsets[start], offsets[stop]
        if lo == hi:
            continue  # no keypoints: every count stays 0
        mask_stack = np.zeros((chunk_frames, height, width), bool)
        for f in range(start, stop):
            if per_frame[f]:
                mask_stack[f - start] = masks.mask(f if key == "frame" else int(t_ns[f]))
        rows = (frame_of[lo:hi] - start, slot[lo:hi])
        pad_xy = np.zeros((chunk_frames, width_n, 2))
        pad_grid = np.zeros((chunk_frames, width_n, 2), np.float32)
        pad_inlier = np.zeros((chunk_frames, width_n), bool)
        pad_valid = np.zeros((chunk_frames, width_n), bool)
        pad_xy[rows] = ixy[lo:hi]
        pad_grid[rows] = grid_xy[lo:hi]
        pad_inlier[rows] = inlier[lo:hi]
        pad_valid[rows] = True
        out_removed, out_full, out_kept = _chunk_kernel(
            mask_stack, pad_xy, pad_grid, pad_inlier, pad_valid, bounds
        )
        removed[lo:hi] = np.asarray(out_removed)[rows]
        n = stop - start
        full[start:stop] = _stack_counts(out_full)[:n]
        kept[start:stop] = _stack_counts(out_kept)[:n]

    if verify:
        _verify(run, keypoints, full, offsets, per_frame, verify_bins)
    frames = run.frames.copy()
    frames["n_extracted"] = kept[:, 0]
    frames["n_inliers"] = kept[:, 1]
    for k, column in enumerate(schema.BIN_COLUMNS):
        frames[column] = kept[:, 2 + k]
    meta = dict(run.meta)
    describe = getattr(masks, "describe", None)
    meta["masks"] = describe() if callable(describe) else type(masks).__name__
    n_removed = np.bincount(frame_of[removed], minlength=n_frames).astype(np.int64)
    return MaskedRun(RunLog(meta=meta, frames=frames, source=run.source), removed, n_removed)


def masked_log(run: RunLog, keypoints: KeypointLog, masks: MaskSource, **options) -> RunLog:
    """`apply_masks(run, keypoints, masks, **options).log`: the run without its dynamic keypoints."""
    return apply_masks(run, keypoints, masks, **options).log


def _stack_counts(counts) -> np.ndarray:
    n_extracted, n_inliers, bins = (np.asarray(c, np.int64) for c in counts)
    return np.concatenate([n_extracted[:, None], n_inliers[:, None], bins], axis=1)


def _verify(run: RunLog, kp: KeypointLog, full: np.ndarray, offsets, per_frame, verify_bins: bool) -> None:
    logged = run.frames
    checks = [("n_extracted", full[:, 0], logged["n_extracted"].to_numpy())]
    checks.append(("n_inliers", full[:, 1], logged["n_inliers"].to_numpy()))
    if verify_bins:
        checks.append(("bins", full[:, 2:], logged[list(schema.BIN_COLUMNS)].to_numpy()))
    for name, mine, theirs in checks:
        bad = mine != theirs if mine.ndim == 1 else (mine != theirs).any(axis=1)
        if not bad.any():
            continue
        f = int(np.argmax(bad))
        t = int(logged["t_ns"].iloc[f])
        line = int(offsets[f]) + 3 if per_frame[f] else None
        if name == "bins":
            k = int(np.argmax(mine[f] != theirs[f]))
            what = f"bin_{k} = {int(mine[f, k])} (the log has {int(theirs[f, k])})"
        else:
            what = f"{name} = {int(mine[f])} (the log has {int(theirs[f])})"
        where = "" if line is not None else " (the file has no keypoint of this frame)"
        raise LogFormatError(
            kp.source,
            line,
            f"frame {f} of {run.source}: its keypoints give {what}{where}: the side file does not "
            "describe this log",
            column="t_ns",
            value=str(t),
        )
