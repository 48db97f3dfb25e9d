"""Masks in ORB-SLAM3's loop against masks applied offline (docs/masks.md, "Masks in the loop").

    python analysis/masks_in_the_loop.py MASKED_LOG UNMASKED_LOG --masks DIR

MASKED_LOG: a run of `jsve frontend run --masks` (its `masks` trailer); UNMASKED_LOG: a run of the same
dataset without masks, with `--keypoints`; DIR: the dataset's mav0/cam0/masks. Checks, and prints:

  * the masked log: per frame, the keypoints as extracted less those dropped are its n_extracted;
  * its own side file, when it has one, holds only kept keypoints (Algorithm 1 removes none of them)
    and reproduces its counts and bins;
  * `jsve mask-logs` on the unmasked run (apply_masks, which first checks that the side file reproduces
    the unmasked log's counts and bins) gives the masked run's n_extracted and bins on every frame both
    runs extracted from the same image with the same extractor: the frames where the masked run's count
    before masking equals the unmasked run's count. ORB-SLAM3 extracts 5 x nFeatures keypoints until a
    map is initialised (mpIniORBextractor), so the two runs extract alike while they initialise alike;
    they part once their tracking does (the first frame whose state differs).

Exit status 1 when a check fails.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from jsve import PngMasks, apply_masks, read_keypoints, read_log
from jsve.io import keypoints_path

BINS = [f"bin_{k}" for k in range(64)]
DYNAMIC = (1, 2)  # cars and pedestrians, as the driver masks them


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("masked", help="log of a run with --masks")
    parser.add_argument("unmasked", help="log of a run without masks, with --keypoints")
    parser.add_argument("--masks", required=True, help="the dataset's mav0/cam0/masks")
    args = parser.parse_args(argv)
    masks = PngMasks(args.masks, classes=DYNAMIC)
    masked, unmasked = read_log(args.masked), read_log(args.unmasked)
    failures = []

    trailer = (masked.trailers or {}).get("masks")
    if trailer is None:
        print(f"{args.masked}: no `masks` trailer (not a run with --masks)", file=sys.stderr)
        return 1
    m = masked.frames
    before, removed = np.asarray(trailer["n_before"]), np.asarray(trailer["n_removed"])
    if not np.array_equal(trailer["t_ns"], m["t_ns"]) or not np.array_equal(
        before - removed, m["n_extracted"]
    ):
        failures.append("the masks trailer does not add up to the masked log's n_extracted")

    side = keypoints_path(args.masked)
    if side.is_file():
        own = apply_masks(masked, read_keypoints(side), masks, key="t_ns")  # verifies counts and bins
        if own.removed.any():
            failures.append(f"{side}: Algorithm 1 still removes {int(own.removed.sum())} kept keypoints")

    offline = apply_masks(
        unmasked, read_keypoints(keypoints_path(args.unmasked)), masks, key="t_ns"
    ).log.frames
    u = unmasked.frames
    if not np.array_equal(u["t_ns"], m["t_ns"]):
        failures.append("the two runs logged different frames")
        same = np.zeros(len(m), bool)
    else:
        same = before == u["n_extracted"].to_numpy()
    counts_equal = offline["n_extracted"].to_numpy() == m["n_extracted"].to_numpy()
    bins_equal = (offline[BINS].to_numpy() == m[BINS].to_numpy()).all(axis=1)
    state_differs = np.flatnonzero(u["state"].to_numpy() != m["state"].to_numpy())
    first_state = int(state_differs[0]) if len(state_differs) else len(m)
    if not (counts_equal & bins_equal)[same].all():
        bad = int(np.flatnonzero(same & ~(counts_equal & bins_equal))[0])
        failures.append(f"frame {bad}: extracted alike, but offline masking gives other counts or bins")
    if not same[: first_state + 1].all():
        failures.append(f"the runs extract differently before their states part (frame {first_state})")

    rows = {
        "frames": len(m),
        "frames with keypoints dropped in the loop": int((removed > 0).sum()),
        "keypoints dropped in the loop": int(removed.sum()),
        "share of keypoints dropped": f"{removed.sum() / max(before.sum(), 1):.1%}",
        "first frame whose state differs": first_state if first_state < len(m) else "never",
        "frames extracted alike (n_before = unmasked n_extracted)": int(same.sum()),
        "... of them with the offline count and bins of the loop": int(
            (same & counts_equal & bins_equal).sum()
        ),
        "frames with the offline count of the loop (all frames)": int(counts_equal.sum()),
    }
    width = max(map(len, rows))
    print("\n".join(f"{key:<{width}}  {value}" for key, value in rows.items()))
    for failure in failures:
        print(f"FAILED: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
