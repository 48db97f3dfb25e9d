"""Level grids of the disturbances: one home for the image layer's registry and for the simulator.

jsve.image._disturb.DISTURBANCES pairs each grid with its image function (OpenCV) and its unit;
jsve.sim._simulate runs the same levels through its vision model, without OpenCV or images. Neither
layer may import the other (analysis/architecture.py), so the grids live here, below both: plain
numbers. docs/disturbances.md gives each disturbance's definition and unit.
"""

from __future__ import annotations

from collections.abc import Iterable

LEVELS: dict[str, tuple[float, ...]] = {
    # The seed paper's three (Rugg-Gunn & Aitken 2022, section 3).
    "blur": tuple(range(0, 55, 5)),  # kernel px
    "downsample": tuple(round(1.0 - 0.1 * i, 1) for i in range(10)),  # scale factor
    "occlusion": tuple(range(50, 500, 50)),  # square side px
    # jsve's further disturbances.
    "noise": (0, 2, 5, 10, 15, 20, 30, 40),  # sigma DN
    "low_light": (1.0, 0.5, 0.3, 0.2, 0.15, 0.1, 0.07, 0.05, 0.03),  # light fraction
    "motion_blur": (0, 5, 10, 15, 20, 30, 40, 50),  # streak px
    "haze": (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0),  # optical depth
    "lens_dirt": (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6),  # mean opacity
}
"""Default levels of every disturbance, in its own unit, in registry order."""

SEED_DISTURBANCES = ("blur", "downsample", "occlusion")
"""The seed paper's disturbances (the first three of LEVELS)."""


def parse_disturbances(spec: str, names: Iterable[str]) -> list[tuple[str, tuple[float, ...] | None]]:
    """The disturbances a spec names, each with its levels, in the order written.

    Syntax (`jsve simulate --disturbances`, `jsve disturb --disturbances`): comma-separated items, each a
    name (its default levels) or `name=level,level,...`: the numbers after `=` up to the next name are
    that name's levels, so "blur=10,20,30,occlusion" is blur at 10, 20 and 30 and occlusion at its
    default levels. The earlier `name:level:level` (jsve simulate's) is read as `name=level,level`.

    Arguments:
        spec: the text. names: the names allowed (disturbances and any keyword the caller expands).
    Returns:
        [(name, levels)], levels None where the spec gives none (the caller's default grid).
    Raises:
        ValueError naming the item: an unknown name, a level that is not a number, a number before any
        name, `name=` without a level.
    """
    allowed = tuple(names)
    out: list[tuple[str, list[float] | None]] = []

    def number(text: str, item: str) -> float:
        try:
            return float(text)
        except ValueError:
            raise ValueError(
                f"disturbances {spec!r}: unknown disturbance {item!r}; choose {', '.join(allowed)} "
                "(levels are numbers after NAME=)"
            ) from None

    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        name, sep, rest = item.partition("=")
        if not sep and ":" in item:  # the earlier name:level:level
            name, _, rest = item.partition(":")
            sep, rest = "=", rest.replace(":", ",")
        name = name.strip()
        if name in allowed:
            levels = [number(v.strip(), item) for v in rest.split(",") if v.strip()] if sep else None
            if sep and not levels:
                raise ValueError(f"disturbances {spec!r}: {item!r} gives no level after '='")
            out.append((name, levels))
        elif sep or not out or out[-1][1] is None:
            if not sep:
                number(item, item)  # not a number: an unknown name
                raise ValueError(f"disturbances {spec!r}: the level {item!r} follows no NAME=")
            raise ValueError(
                f"disturbances {spec!r}: unknown disturbance {name!r}; choose {', '.join(allowed)}"
            )
        else:
            out[-1][1].append(number(item, item))
    return [(name, None if levels is None else tuple(levels)) for name, levels in out]
