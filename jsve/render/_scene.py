"""The rendered world: a closed room around a trajectory, furniture that occludes, a photographic texture.

    make_scene(positions, rng, textures)   room + furniture for camera centres [N, 3] (world frame, m)
    Scene                                  boxes (axis-aligned), and where each face lies in the texture atlas
    mosaic_texture / procedural_texture    the atlas's texels: crops of real images, or a generated pattern

Everything is axis-aligned in EuRoC's world frame (z up): the room is one box seen from inside, the
furniture a set of boxes seen from outside (tables: a top on four legs; shelves: a frame with boards;
pillars; crates: stacks), so the scene is non-convex and objects hide each other and the walls as the
camera moves. Every face has a rectangle of the texture atlas at `texel_m` metres per texel (5 mm:
about one texel per pixel at 3 m with EuRoC's 458 px focal length), so the texture has the same scale on
every surface and the atlas's mip levels antialias it (jsve.render._raster).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jsve.render._objects import MovingObjects, ObjectsConfig, place_objects

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")

ATLAS_WIDTH = 8192
"""Texels per atlas row of level 0; the levels side by side (mip_layout) stay below the 32767 texels in each
direction that cv2.remap addresses."""

MIP_LEVELS = 7
"""Atlas levels 0 (texel_m) to 6 (64 texel_m)."""

_PAD = 2 ** (MIP_LEVELS - 1)
"""Texels of texture around each face rectangle, so coarse levels do not blend a neighbour in."""


@dataclass(frozen=True)
class SceneConfig:
    """How the room and its furniture are laid out.

    Attributes:
        margin_m: walls this far beyond the camera centres' extent (m, horizontal).
        floor_m, ceiling_m: floor below the lowest and ceiling above the highest camera centre (m).
        clearance_m: no furniture closer than this to any camera centre (m).
        n_furniture: furniture pieces to place (each is 1 to 6 boxes).
        texel_m: texture scale, m per texel.
    """

    margin_m: float = 3.0
    floor_m: float = 1.2
    ceiling_m: float = 1.5
    clearance_m: float = 0.8
    n_furniture: int = 14
    texel_m: float = 0.005


@dataclass(frozen=True)
class Scene:
    """Axis-aligned boxes; box 0 is the room, seen from inside; the others are seen from outside.

    Attributes:
        lo, hi: [B, 3] box corners, m, world frame.
        face_origin: [B, 6, 2] atlas texel (x, y) of each face's (u, v) = (0, 0) corner. Face f = 2 a + s is
            the face normal to axis a on the low (s = 0) or high (s = 1) side; its texture axes (u, v) are
            the two other world axes in increasing order, in texels (world / texel_m).
        shade: [B, 6] brightness factor of each face (light from above, so faces differ).
        texel_m: m per texel.
        mip: [H, 3 W / 2] uint8, every texture level in one image (mip_layout): a pixel's trilinear sample is
            two cv2.remap calls whatever its level, with no sorting of pixels by level.
        mip_origin: [MIP_LEVELS, 2] float32 texel (x, y) of each level's corner in mip.
        atlas: [MIP_LEVELS] views of mip's levels (level l is level l - 1 smoothed and halved).
        texture_source: what the texels came from ("mosaic of N images in DIR" or "procedural").
        objects: the dynamic objects, boxes n_static .. n_boxes - 1 (their lo and hi where they are at
            t = 0; `at` moves them), or None.
        n_static: boxes that never move (the room and its furniture).
    """

    lo: np.ndarray
    hi: np.ndarray
    face_origin: np.ndarray
    shade: np.ndarray
    texel_m: float
    mip: np.ndarray
    mip_origin: np.ndarray
    atlas: tuple[np.ndarray, ...]
    texture_source: str
    objects: MovingObjects | None = None
    n_static: int = 0

    @property
    def n_boxes(self) -> int:
        return len(self.lo)

    def at(self, t_s: float) -> Scene:
        """The scene with its objects where they are at t_s (s from the sequence's start); the faces keep
        their texture rectangles, so an object's texture moves with it."""
        if not self.objects:
            return self
        lo = self.lo.copy()
        lo[self.n_static :] = self.objects.lo_at(t_s)
        hi = lo.copy()
        hi[: self.n_static] = self.hi[: self.n_static]
        hi[self.n_static :] += self.objects.size
        return dataclasses.replace(self, lo=lo, hi=hi)

    def instance_ids(self) -> np.ndarray:
        """[n_boxes] uint16 KITTI MOTS object id of every box, 0 for the room and the furniture."""
        ids = np.zeros(self.n_boxes, np.uint16)
        if self.objects:
            ids[self.n_static :] = self.objects.obj_id
        return ids


# --------------------------------------------------------------------------------------------------
# Layout


def _furniture(
    rng: np.random.Generator, room_lo: np.ndarray, room_hi: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray]]:
    """One furniture piece standing on the floor, as boxes (lo, hi); position drawn inside the room."""
    floor = room_lo[2]
    kind = rng.choice(["table", "shelf", "pillar", "crates"], p=[0.3, 0.25, 0.2, 0.25])
    size = {
        "table": (rng.uniform(0.8, 1.8), rng.uniform(0.6, 1.0), rng.uniform(0.7, 1.0)),
        "shelf": (rng.uniform(0.8, 2.0), rng.uniform(0.35, 0.5), rng.uniform(1.4, 2.2)),
        "pillar": (rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6), room_hi[2] - floor),
        "crates": (rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0), rng.uniform(0.4, 0.8)),
    }[kind]
    sx, sy, sz = size
    if rng.random() < 0.5:
        sx, sy = sy, sx
    x0 = rng.uniform(room_lo[0] + 0.1, room_hi[0] - 0.1 - sx)
    y0 = rng.uniform(room_lo[1] + 0.1, room_hi[1] - 0.1 - sy)
    lo, hi = np.array([x0, y0, floor]), np.array([x0 + sx, y0 + sy, floor + sz])

    def box(a, b):
        return np.array(a, float), np.array(b, float)

    if kind == "table":
        top = 0.05
        leg = 0.06
        boxes = [box([lo[0], lo[1], hi[2] - top], hi)]
        for cx in (lo[0], hi[0] - leg):
            for cy in (lo[1], hi[1] - leg):
                boxes.append(box([cx, cy, floor], [cx + leg, cy + leg, hi[2] - top]))
        return boxes
    if kind == "shelf":
        side, board = 0.04, 0.03
        boxes = [box(lo, [lo[0] + side, hi[1], hi[2]]) if sx < sy else box(lo, [hi[0], lo[1] + side, hi[2]])]
        boxes.append(
            box([hi[0] - side, lo[1], lo[2]], hi) if sx < sy else box([lo[0], hi[1] - side, lo[2]], hi)
        )
        for z in np.linspace(floor + 0.1, hi[2] - board, rng.integers(3, 5)):
            boxes.append(box([lo[0], lo[1], z], [hi[0], hi[1], z + board]))
        return boxes
    if kind == "crates":
        boxes = [box(lo, hi)]
        top = rng.uniform(0.5, 0.9, 2) * np.array([sx, sy])
        shift = rng.uniform(0, 1, 2) * (np.array([sx, sy]) - top)
        corner = np.array([x0 + shift[0], y0 + shift[1], hi[2]])
        boxes.append(box(corner, corner + [top[0], top[1], rng.uniform(0.3, 0.6)]))
        return boxes
    return [box(lo, hi)]


def _distance_to_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Euclidean distance of points [N, 3] to an axis-aligned box (0 inside)."""
    return np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=-1)


def layout(positions: np.ndarray, rng: np.random.Generator, config: SceneConfig = SceneConfig()):
    """Room and furniture boxes (lo [B, 3], hi [B, 3]) for camera centres [N, 3]; box 0 is the room."""
    positions = np.asarray(positions, float).reshape(-1, 3)
    lo = positions.min(0) - [config.margin_m, config.margin_m, config.floor_m]
    hi = positions.max(0) + [config.margin_m, config.margin_m, config.ceiling_m]
    boxes = [(lo, hi)]
    placed, tries = 0, 0
    while placed < config.n_furniture and tries < 50 * config.n_furniture:
        tries += 1
        piece = _furniture(rng, lo, hi)
        piece_lo = np.min([b[0] for b in piece], axis=0)
        piece_hi = np.max([b[1] for b in piece], axis=0)
        if _distance_to_box(positions, piece_lo, piece_hi).min() < config.clearance_m:
            continue
        if any(np.all(piece_lo < b_hi) and np.all(b_lo < piece_hi) for b_lo, b_hi in boxes[1:]):
            continue
        boxes.extend(piece)
        placed += 1
    return np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes])


# --------------------------------------------------------------------------------------------------
# Texture


def image_files(folder: str | os.PathLike) -> list[Path]:
    """Image files under a folder (recursively, sorted)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such texture folder")
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise FileNotFoundError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) to texture with")
    return files


def mosaic_texture(
    images: Sequence[np.ndarray],
    shape: tuple[int, int],
    rng: np.random.Generator,
    tile: tuple[int, int] = (96, 256),
) -> np.ndarray:
    """A non-periodic mosaic of random crops of the images, randomly flipped and turned by 90 degrees.

    Tiles of random size (tile: min and max side, texels) in rows of random height; each crop's contrast and
    brightness are jittered (x0.8-1.2, +-15 grey levels), so repeated content never lines up.

    Returns:
        [H, W] uint8 grey levels (each tile rounded and clipped: the atlas's 8 bits, with no float copy of
        a 200 MB atlas).
    """
    height, width = shape
    out = np.empty((height, width), np.uint8)
    y = 0
    while y < height:
        row_h = min(int(rng.integers(tile[0], tile[1] + 1)), height - y)
        x = 0
        while x < width:
            tile_w = min(int(rng.integers(tile[0], tile[1] + 1)), width - x)
            source = images[int(rng.integers(len(images)))]
            turns = int(rng.integers(4))
            need_h, need_w = (tile_w, row_h) if turns % 2 else (row_h, tile_w)
            sy = int(rng.integers(0, max(1, source.shape[0] - need_h + 1)))
            sx = int(rng.integers(0, max(1, source.shape[1] - need_w + 1)))
            crop = source[sy : sy + need_h, sx : sx + need_w]
            if crop.shape != (need_h, need_w):
                crop = cv2.resize(crop, (need_w, need_h), interpolation=cv2.INTER_LINEAR)
            crop = np.rot90(crop, turns)
            if rng.random() < 0.5:
                crop = crop[:, ::-1]
            mean = float(crop.mean())
            gain, offset = rng.uniform(0.8, 1.2), rng.uniform(-15, 15)
            jittered = (crop - mean) * gain + mean + offset
            out[y : y + row_h, x : x + tile_w] = np.clip(np.rint(jittered), 0, 255)
            x += tile_w
        y += row_h
    return out


def procedural_texture(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A deterministic corner-rich pattern, used when no photographs are given.

    Multi-scale value noise (cells of 4 to 256 texels) under random filled rectangles, discs and line
    segments of random grey levels at sizes of 6 to 120 texels: edges and corners at every scale, as FAST
    needs. Not photographic: say so where it is used.

    Returns:
        [H, W] float32 grey levels (0-255 scale).
    """
    height, width = shape
    out = np.zeros((height, width), np.float32)
    for cell, amplitude in ((256, 40.0), (64, 25.0), (16, 18.0), (4, 10.0)):
        coarse = rng.normal(0.0, amplitude, (height // cell + 2, width // cell + 2)).astype(np.float32)
        out += cv2.resize(
            coarse, (coarse.shape[1] * cell, coarse.shape[0] * cell), interpolation=cv2.INTER_CUBIC
        )[:height, :width]
    out += 110.0
    n_shapes = height * width // 900
    kinds = rng.integers(0, 3, n_shapes)
    centres = rng.uniform(0, 1, (n_shapes, 2)) * [width, height]
    sizes = np.exp(rng.uniform(np.log(6), np.log(120), (n_shapes, 2)))
    levels = rng.uniform(20, 235, n_shapes)
    for kind, (cx, cy), (sw, sh), level in zip(kinds, centres, sizes, levels, strict=True):
        colour = float(level)
        if kind == 0:
            cv2.rectangle(out, (int(cx), int(cy)), (int(cx + sw), int(cy + sh)), colour, -1)
        elif kind == 1:
            cv2.circle(out, (int(cx), int(cy)), int(sw / 2), colour, -1)
        else:
            cv2.line(out, (int(cx), int(cy)), (int(cx + sw), int(cy + sh - sw)), colour, max(1, int(sh / 20)))
    return out


def load_texture_images(folder: str | os.PathLike, limit: int = 400) -> list[np.ndarray]:
    """Grey images of a texture folder (at most `limit`, spread evenly over the sorted files)."""
    files = image_files(folder)
    if len(files) > limit:
        files = [files[i] for i in np.linspace(0, len(files) - 1, limit).round().astype(int)]
    images = []
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(f"{path}: not a readable image")
        images.append(image.astype(np.float32))
    return images


# --------------------------------------------------------------------------------------------------
# Atlas


def _face_extents(lo: np.ndarray, hi: np.ndarray, texel_m: float) -> np.ndarray:
    """[B, 6, 2] texel width and height of every face's (u, v) rectangle."""
    size = np.ceil((hi - lo) / texel_m).astype(np.int64) + 1
    ext = np.zeros((len(lo), 6, 2), np.int64)
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        ext[:, 2 * axis] = ext[:, 2 * axis + 1] = np.stack([size[:, u], size[:, v]], -1)
    return ext


def _pack(extents: np.ndarray) -> tuple[np.ndarray, int]:
    """Shelf packing of rectangles [R, 2] (w, h) into ATLAS_WIDTH columns, each padded by _PAD texels and
    aligned to the coarsest level; returns the (x, y) origins [R, 2] and the atlas height."""
    align = 2 ** (MIP_LEVELS - 1)
    padded = ((extents + 2 * _PAD + align - 1) // align) * align
    if padded[:, 0].max() > ATLAS_WIDTH:
        raise ValueError(f"a face of {extents[:, 0].max()} texels is wider than the atlas ({ATLAS_WIDTH})")
    origin = np.zeros_like(extents)
    order = np.argsort(-padded[:, 1], kind="stable")
    x = y = shelf = 0
    for i in order:
        w, h = padded[i]
        if x + w > ATLAS_WIDTH:
            x, y, shelf = 0, y + shelf, 0
        origin[i] = (x + _PAD, y + _PAD)
        x += w
        shelf = max(shelf, h)
    height = y + shelf
    if height >= 32767:  # cv2.remap's limit (mip_layout keeps the levels within the atlas's height)
        raise ValueError(
            f"the texture atlas needs {height} rows (at most 32766): a smaller room or a coarser texel_m"
        )
    return origin, int(height)


def _shade(n_boxes: int) -> np.ndarray:
    """Brightness per face: ambient plus a light from above and one side (room faces look inward)."""
    light = np.array([0.35, 0.55, 0.76])
    light /= np.linalg.norm(light)
    normals = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float)
    outside = 0.55 + 0.45 * np.clip(normals @ light, 0.0, None)
    inside = 0.55 + 0.45 * np.clip(-normals @ light, 0.0, None)
    return np.concatenate([inside[None], np.repeat(outside[None], n_boxes - 1, axis=0)])


def mip_layout(height: int, width: int) -> np.ndarray:
    """[MIP_LEVELS, 2] (x, y) corners of the levels of an atlas of height x width (multiples of
    2 ** (MIP_LEVELS - 1)) in one image of height x 3 width / 2: level 0 on the left, level 1 to its right,
    levels 2 and coarser side by side under level 1."""
    origin = [(0, 0), (width, 0)]
    x = width
    for level in range(2, MIP_LEVELS):
        origin.append((x, height // 2))
        x += width >> level
    return np.array(origin, np.int64)


def _paint_objects(
    base: np.ndarray, origin: np.ndarray, extents: np.ndarray, rng: np.random.Generator
) -> None:
    """Give the faces' rectangles (origin, extents [R, 2], texels, padding included) a procedural texture
    in place: the objects' own texture, distinct from the room's photographs."""
    for (x, y), (w, h) in zip(origin, extents, strict=True):
        x0, y0 = x - _PAD, y - _PAD
        patch = procedural_texture((h + 2 * _PAD, w + 2 * _PAD), rng)
        base[y0 : y0 + h + 2 * _PAD, x0 : x0 + w + 2 * _PAD] = np.clip(np.rint(patch), 0, 255)


def with_objects(
    positions: np.ndarray, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator, objects: ObjectsConfig
) -> tuple[np.ndarray, np.ndarray, MovingObjects]:
    """The static boxes (lo, hi) followed by the objects' boxes at t = 0, and the objects."""
    placed = place_objects(positions, lo[0], hi[0], (lo[1:], hi[1:]), rng, objects)
    at_zero = placed.lo_at(0.0)
    return np.vstack([lo, at_zero]), np.vstack([hi, at_zero + placed.size]), placed


def make_scene(
    positions: np.ndarray,
    rng: np.random.Generator,
    textures: Sequence[np.ndarray] | None = None,
    config: SceneConfig = SceneConfig(),
    texture_source: str = "",
    objects: ObjectsConfig | None = None,
    objects_rng: np.random.Generator | None = None,
) -> Scene:
    """The room, its furniture, its dynamic objects and their texture for camera centres [N, 3] (m, world).

    Arguments:
        positions: where the camera goes (the furniture keeps config.clearance_m from every one).
        rng: draws the layout and the texture.
        textures: grey images (float or uint8) to build the mosaic from; None: procedural texture.
        texture_source: a description for the dataset's manifest.
        objects, objects_rng: the dynamic objects and the generator that places and textures them.
    """
    lo, hi = layout(positions, rng, config)
    n_static, placed = len(lo), None
    if objects is not None and objects.count:
        lo, hi, placed = with_objects(positions, lo, hi, objects_rng, objects)
    face_extents = _face_extents(lo, hi, config.texel_m)
    extents = face_extents.reshape(-1, 2)
    origin, height = _pack(extents)
    shape = (height, ATLAS_WIDTH)
    if textures:
        base = mosaic_texture(textures, shape, rng)
        source = texture_source or f"mosaic of {len(textures)} images"
    else:
        base = procedural_texture(shape, rng)
        source = "procedural (no --texture given)"
    if placed is not None:
        base = base if base.dtype == np.uint8 else np.clip(np.rint(base), 0, 255).astype(np.uint8)
        _paint_objects(base, origin[6 * n_static :], extents[6 * n_static :], objects_rng)
    origins = mip_layout(height, ATLAS_WIDTH)
    mip = np.zeros((height, ATLAS_WIDTH * 3 // 2), np.uint8)  # 8 bits, as photographs: a quarter the memory
    mip[:, :ATLAS_WIDTH] = base if base.dtype == np.uint8 else np.clip(np.rint(base), 0, 255)
    del base
    levels = [mip[:, :ATLAS_WIDTH]]
    for (x, y), level in zip(origins[1:], range(1, MIP_LEVELS), strict=True):
        h, w = height >> level, ATLAS_WIDTH >> level
        mip[y : y + h, x : x + w] = cv2.pyrDown(levels[-1], dstsize=(w, h))
        levels.append(mip[y : y + h, x : x + w])
    return Scene(
        lo=lo,
        hi=hi,
        face_origin=origin.reshape(len(lo), 6, 2).astype(np.float32),
        shade=_shade(len(lo)).astype(np.float32),
        texel_m=config.texel_m,
        mip=mip,
        mip_origin=origins.astype(np.float32),
        atlas=tuple(levels),
        texture_source=source,
        objects=placed,
        n_static=n_static,
    )
