"""Level grids of the disturbances: one home for the image layer's registry and for the simulator.

jsve.image._disturb.DISTURBANCES pairs each grid with its image function (OpenCV) and its unit;
jsve.sim._simulate runs the same levels through its vision model, without OpenCV or images. Neither
layer may import the other (analysis/architecture.py), so the grids live here, below both: plain
numbers. docs/disturbances.md gives each disturbance's definition and unit.
"""

from __future__ import annotations

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
