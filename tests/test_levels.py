"""jsve.core._levels: the level grids and the disturbance spec of `jsve simulate` and `jsve disturb`."""

from __future__ import annotations

import pytest

from jsve.core._levels import LEVELS, SEED_DISTURBANCES, parse_disturbances

NAMES = ("seed", *LEVELS)


def test_seed_disturbances_are_the_first_three_grids():
    assert tuple(LEVELS)[:3] == SEED_DISTURBANCES == ("blur", "downsample", "occlusion")


@pytest.mark.parametrize(
    ("spec", "parsed"),
    [
        ("blur", [("blur", None)]),
        ("blur=10,20,30", [("blur", (10.0, 20.0, 30.0))]),
        ("blur=10,20,30,occlusion", [("blur", (10.0, 20.0, 30.0)), ("occlusion", None)]),
        ("blur, occlusion=100,200 ,noise", [("blur", None), ("occlusion", (100.0, 200.0)), ("noise", None)]),
        ("downsample=0.5,0.25", [("downsample", (0.5, 0.25))]),
        ("seed,haze=1.5", [("seed", None), ("haze", (1.5,))]),
        # jsve simulate's earlier spelling
        ("blur:0:25:50,noise", [("blur", (0.0, 25.0, 50.0)), ("noise", None)]),
        ("", []),
    ],
)
def test_a_spec_names_disturbances_with_their_levels(spec, parsed):
    assert parse_disturbances(spec, NAMES) == parsed


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("fog", "unknown disturbance 'fog'; choose seed, blur"),
        ("fog=3", "unknown disturbance 'fog'"),
        ("blur=5,fog", "unknown disturbance 'fog'"),
        ("10,blur", "the level '10' follows no NAME="),
        ("blur,10", "the level '10' follows no NAME="),
        ("blur=", "'blur=' gives no level after '='"),
    ],
)
def test_a_bad_spec_names_the_item(spec, message):
    with pytest.raises(ValueError, match=message):
        parse_disturbances(spec, NAMES)
