"""Dynamic objects of a rendered scene: car-sized boxes and pedestrian-sized columns moving on paths.

    ObjectsConfig                          how many cars and pedestrians, how many parked, how fast
    place_objects(positions, boxes, rng)   MovingObjects on paths clear of the cameras and the furniture
    MovingObjects.lo_at(t_s)               every object's box corner at a time

An object is an axis-aligned box that translates back and forth along a straight path on the floor,
parallel to a wall (x or y), at a constant speed (a parked object has speed 0 and stands where its phase
puts it on its path). Objects keep `clearance_m` from every camera centre of the trajectory over their
whole path and never overlap the furniture or each other's paths, so they occlude the room and each
other without passing through anything. Their faces carry their own texture (jsve.render._scene), which
moves with them, so features on them move against the room's: what Masked ORB-SLAM3 removes.

Object ids follow KITTI MOTS: obj_id = class_id * 1000 + instance, class 1 a car, 2 a pedestrian.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CAR, PEDESTRIAN = 1, 2
"""KITTI MOTS class ids."""

_SIZES = {
    CAR: ((3.6, 4.6), (1.6, 1.9), (1.4, 1.6)),  # length, width, height, m
    PEDESTRIAN: ((0.4, 0.6), (0.3, 0.45), (1.6, 1.9)),
}
_PATH_M = {CAR: (3.0, 7.0), PEDESTRIAN: (2.0, 5.0)}


@dataclass(frozen=True)
class ObjectsConfig:
    """The dynamic objects of a rendered scene.

    Attributes:
        cars, pedestrians: how many of each.
        parked: how many objects stand still (the first ones placed, cars first), or "all".
        car_speed_mps, pedestrian_speed_mps: speed ranges of the moving ones, m/s.
        clearance_m: no object closer than this to any camera centre, anywhere on its path (m).
    """

    cars: int = 0
    pedestrians: int = 0
    parked: int | str = 0
    car_speed_mps: tuple[float, float] = (1.0, 2.5)
    pedestrian_speed_mps: tuple[float, float] = (0.6, 1.4)
    clearance_m: float = 2.0

    @property
    def count(self) -> int:
        return self.cars + self.pedestrians

    def n_parked(self) -> int:
        """How many objects stand still."""
        return self.count if self.parked == "all" else min(int(self.parked), self.count)


@dataclass(frozen=True)
class MovingObjects:
    """Objects on straight back-and-forth paths.

    Attributes:
        start, end: [M, 3] the box's low corner at the two ends of its path, m, world frame.
        size: [M, 3] box extent, m.
        speed: [M] m/s along the path (0: parked).
        phase_m: [M] distance travelled at t = 0, m (along the path and back: 0 to 2 length).
        obj_id: [M] int, class_id * 1000 + instance.
    """

    start: np.ndarray
    end: np.ndarray
    size: np.ndarray
    speed: np.ndarray
    phase_m: np.ndarray
    obj_id: np.ndarray

    def __len__(self) -> int:
        return len(self.obj_id)

    @property
    def class_id(self) -> np.ndarray:
        return self.obj_id // 1000

    def lo_at(self, t_s: float) -> np.ndarray:
        """[M, 3] low box corners at time t_s (s from the sequence's start), m."""
        length = np.linalg.norm(self.end - self.start, axis=1)
        travelled = np.mod(self.phase_m + self.speed * t_s, 2 * length)
        along = np.where(travelled <= length, travelled, 2 * length - travelled) / length
        return self.start + along[:, None] * (self.end - self.start)

    def describe(self) -> list[dict]:
        """One dict per object for a manifest: id, class, size, path ends, speed."""
        names = {CAR: "car", PEDESTRIAN: "pedestrian"}
        return [
            {
                "obj_id": int(self.obj_id[i]),
                "class": names[int(self.class_id[i])],
                "size_m": self.size[i].round(3).tolist(),
                "path_start_m": self.start[i].round(3).tolist(),
                "path_end_m": self.end[i].round(3).tolist(),
                "speed_mps": round(float(self.speed[i]), 3),
            }
            for i in range(len(self))
        ]


def _distance_to_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=-1)


def _overlaps(lo: np.ndarray, hi: np.ndarray, los: np.ndarray, his: np.ndarray) -> bool:
    """Whether box (lo, hi) overlaps any of boxes (los, his [K, 3])."""
    return bool(len(los)) and bool(np.any(np.all(lo < his, axis=1) & np.all(los < hi, axis=1)))


def _draw_object(rng: np.random.Generator, kind: int, room_lo: np.ndarray, room_hi: np.ndarray):
    """(start, end, size) of one candidate: a box on the floor and a path parallel to x or y."""
    length, width, height = (rng.uniform(*r) for r in _SIZES[kind])
    axis = int(rng.integers(2))
    size = np.array([length, width, height]) if axis == 0 else np.array([width, length, height])
    path = min(rng.uniform(*_PATH_M[kind]), float(room_hi[axis] - room_lo[axis] - size[axis] - 0.2))
    span_lo = room_lo[:2] + 0.1
    span_hi = room_hi[:2] - 0.1 - size[:2]
    span_hi[axis] -= path
    start = np.append(rng.uniform(span_lo, np.maximum(span_hi, span_lo)), room_lo[2])
    end = start.copy()
    end[axis] += path
    return start, end, size


def place_objects(
    positions: np.ndarray,
    room_lo: np.ndarray,
    room_hi: np.ndarray,
    furniture: tuple[np.ndarray, np.ndarray],
    rng: np.random.Generator,
    config: ObjectsConfig,
    tries: int = 3000,
) -> MovingObjects:
    """Objects on paths that keep clear of the cameras, the furniture and each other.

    Arguments:
        positions: [N, 3] camera centres, m. room_lo, room_hi: the room's corners, m.
        furniture: (lo [F, 3], hi [F, 3]) boxes the paths must not cross.
        rng: draws sizes, paths, speeds and phases.
        tries: candidates drawn per object before giving up.
    Raises:
        ValueError when an object finds no free path (a larger room margin or fewer objects help).
    """
    kinds = [CAR] * config.cars + [PEDESTRIAN] * config.pedestrians
    taken_lo, taken_hi = (np.asarray(b, float).reshape(-1, 3) for b in furniture)
    rows, counts = [], {CAR: 0, PEDESTRIAN: 0}
    for k, kind in enumerate(kinds):
        for _ in range(tries):
            start, end, size = _draw_object(rng, kind, room_lo, room_hi)
            swept_lo, swept_hi = np.minimum(start, end), np.maximum(start, end) + size
            if _distance_to_box(positions, swept_lo, swept_hi).min() < config.clearance_m:
                continue
            if _overlaps(swept_lo, swept_hi, taken_lo, taken_hi):
                continue
            break
        else:
            raise ValueError(
                f"object {k + 1} of {len(kinds)} ({'car' if kind == CAR else 'pedestrian'}) found no path "
                f"{config.clearance_m} m clear of the cameras and clear of the furniture and the other "
                f"objects in {tries} tries: ask for fewer objects or a larger room margin"
            )
        taken_lo = np.vstack([taken_lo, swept_lo])
        taken_hi = np.vstack([taken_hi, swept_hi])
        counts[kind] += 1
        speed_range = config.car_speed_mps if kind == CAR else config.pedestrian_speed_mps
        # Drawn either way, so parking objects changes no other draw: a parked variant of a scene has
        # the same objects in the same places, standing.
        speed = rng.uniform(*speed_range) * (k >= config.n_parked())
        phase = rng.uniform(0.0, 2.0) * np.linalg.norm(end - start)
        rows.append((start, end, size, speed, phase, kind * 1000 + counts[kind]))
    if not rows:
        empty = np.zeros((0, 3))
        return MovingObjects(empty, empty, empty, np.zeros(0), np.zeros(0), np.zeros(0, np.int64))
    start, end, size, speed, phase, ids = zip(*rows, strict=True)
    return MovingObjects(
        start=np.array(start),
        end=np.array(end),
        size=np.array(size),
        speed=np.array(speed, float),
        phase_m=np.array(phase, float),
        obj_id=np.array(ids, np.int64),
    )
