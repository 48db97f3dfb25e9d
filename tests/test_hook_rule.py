"""The rule the hook runs in ORB-SLAM3's loop (jsve_orbslam3_hook.hpp) against jsve's own.

tests/cpp/hook_rule.cpp compiles the hook's score and success test without ORB-SLAM3 and prints them
for random frames and rules: every preset (the authors' Eq.1 and Option 1 builds, Option 2, ORB-SLAM3's
inlier count) and random members of the SVE family (p, q through 0, negative and positive; rho; weights
at 0 and 1), on counts with empty bins, zero inliers and zero frustum. The oracle is jsve.core
(Combination.score over frame_features, tracking_succeeds) in float64: a rule run in the loop and the
same rule replayed must take the same decision, or identity replay of a rule's own runs fails.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jsve.frontend
from jsve.core import preset
from jsve.core._machine import HardLogic, tracking_succeeds
from jsve.core._rules import InlierRule
from jsve.core._sve import INPUTS, Combination, frame_features

CXX = shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")
HOOK_DIR = Path(jsve.frontend.__file__).resolve().parent / "orbslam3"
SOURCE = Path(__file__).resolve().parent / "cpp" / "hook_rule.cpp"
STRICT = ["-Wall", "-Wextra", "-Wpedantic", "-Werror", "-Wconversion", "-Wshadow"]


@pytest.fixture(scope="module")
def hook_rule(tmp_path_factory):
    if CXX is None:
        pytest.skip("no C++ compiler (g++, c++ or clang++) on PATH")
    exe = tmp_path_factory.mktemp("hook") / "hook_rule"
    cmd = [CXX, "-std=c++17", "-O1", *STRICT, f"-I{jsve.frontend.get_include()}", f"-I{HOOK_DIR}"]
    done = subprocess.run([*cmd, str(SOURCE), "-o", str(exe)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return exe


def _cases(seed: int, n: int = 400):
    """Random (rule, counts, flags) cases: presets and random SVE rules over awkward counts."""
    rng = np.random.default_rng(seed)
    rules = [preset(name) for name in ("orbslam3", "sve-eq1", "sve-option1", "sve-option2", "jsve-option1")]
    for _ in range(n):
        if rng.random() < 0.4:
            rule = rules[rng.integers(len(rules))]
        else:
            c = Combination(
                w_a=rng.choice([0.0, 1.0, rng.random()]), u_b=rng.choice([0.0, 1.0, rng.random()]),
                p=rng.choice([0.0, 1e-8, -1.5, 2.0, rng.normal()]), q=rng.choice([0.0, 1.0, rng.normal()]),
                rho=rng.choice([0.25, 0.5, rng.uniform(0.05, 1.0)]),
            )  # fmt: skip
            rule = preset("sve-option2").__class__(c, preset("sve-option2").thresholds)
        n_ext = int(rng.choice([0, 1, rng.integers(1, 1500)]))
        bins = np.zeros(64, int)
        if n_ext:
            on = rng.random(64) < rng.choice([0.05, 0.5, 1.0])
            weights = rng.random(64) * on
            if weights.sum() > 0:
                bins = rng.multinomial(int(n_ext * rng.uniform(0.5, 1.0)), weights / weights.sum())
        n_inl = int(rng.integers(0, n_ext + 1))
        n_fru = int(rng.choice([0, rng.integers(1, 2000)]))
        flags = rng.integers(0, 2, 4)
        yield rule, (n_ext, n_inl, n_fru, bins), flags


def _line(rule, counts, flags, n_features=1000.0) -> str:
    n_ext, n_inl, n_fru, bins = counts
    t = rule.thresholds
    th = [float(x) for x in (t.imu_init, t.not_init, t.reloc, t.recovery)]
    if isinstance(rule, InlierRule):
        head = [0, 0, 0.5, 0.5, 1.0, 1.0, 0.25]
    else:
        c = rule.combination
        head = [1, INPUTS.index(c.inputs)] + [float(x) for x in (c.w_a, c.u_b, c.p, c.q, c.rho)]
    numbers = head + [n_features] + th + [n_ext, n_inl, n_fru, *bins.tolist(), *flags.tolist()]
    return " ".join(repr(x) if isinstance(x, float) else str(x) for x in numbers)


def _oracle(rule, counts, flags, n_features=1000.0):
    n_ext, n_inl, n_fru, bins = counts
    f = frame_features(n_ext, n_inl, n_fru, jnp.asarray(bins), n_features)
    score = float(rule.score(f))
    in_reloc, recently_lost, imu_ok, stereo = (float(x) for x in flags)
    ok = tracking_succeeds(HardLogic(), score, rule.thresholds, recently_lost, imu_ok, in_reloc, stereo)
    return score, bool(float(ok) > 0.5)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_hook_scores_and_decides_as_jsve(hook_rule, seed, x64):
    cases = list(_cases(seed))  # built under x64: the rules' leaves are float64
    text = "\n".join(_line(*c) for c in cases) + "\n"
    out = subprocess.run([str(hook_rule)], input=text, capture_output=True, text=True, check=True).stdout
    rows = [line.split() for line in out.splitlines()]
    assert len(rows) == len(cases)
    for (rule, counts, flags), (score_text, ok_text) in zip(cases, rows, strict=True):
        score, ok = _oracle(rule, counts, flags)
        assert float(score_text) == pytest.approx(score, rel=1e-12, abs=1e-13), (rule, counts)
        assert (ok_text == "1") == ok, (rule, counts, flags, score)


def test_the_driver_reads_every_rule_jsve_frontend_run_passes(hook_rule):
    """The driver's --rule-inliers / --rule-sve, as `jsve.frontend._run.driver_rule` writes them for every
    preset, parsed by the hook's parse_rule into the rule's own numbers."""
    from jsve.core import PRESETS
    from jsve.frontend._run import driver_rule

    for name in PRESETS:
        args, _ = driver_rule(name, preset(name), "imu-coast")
        out = subprocess.run([str(hook_rule), "--parse", args[0], args[1]], capture_output=True, text=True)
        assert out.returncode == 0, (name, args, out.stdout)
        kind, inputs, *numbers = out.stdout.split()
        rule = preset(name)
        t = rule.thresholds
        expected = [float(x) for x in (t.imu_init, t.not_init, t.reloc, t.recovery)]
        if isinstance(rule, InlierRule):
            assert kind == "0"
        else:
            c = rule.combination
            assert kind == "1" and int(inputs) == INPUTS.index(c.inputs)
            expected = [float(x) for x in (c.w_a, c.u_b, c.p, c.q, c.rho)] + expected
        assert [float(x) for x in numbers[-len(expected) :]] == expected, name
    for flag, text, message in (
        ("--rule-sve", "jsve,0.5,0.5,0,1,0.25,0.06,0.2,0.2", "wants INPUTS"),
        ("--rule-sve", "authors-eq1,0.2,0.5,0,1,0.5,0.1,0.3,0.3,0.1", "P and Q must be 1"),
        ("--rule-sve", "mine,0.5,0.5,0,1,0.25,0.06,0.2,0.2,0.04", "INPUTS must be"),
        ("--rule-inliers", "15,50,50,1O", "'1O' is not a number"),
    ):
        out = subprocess.run([str(hook_rule), "--parse", flag, text], capture_output=True, text=True)
        assert out.returncode == 1 and message in out.stdout, (text, out.stdout)


def test_the_hook_logs_the_stamp_of_the_image_name(hook_rule):
    """EuRoC names images by their 19-digit stamp: the log's t_ns is that stamp exactly, which the
    double ORB-SLAM3 holds (1.4e9 s, spaced 2.4e-7 s) cannot give; other names fall back to it."""

    def stamp(name: str, seconds: str) -> int:
        out = subprocess.run([str(hook_rule), "--stamp", name, seconds], capture_output=True, text=True)
        return int(out.stdout)

    t = 1403715274612143104
    assert stamp(f"d/mav0/cam0/data/{t}.png", repr(t * 1e-9)) == t
    assert round(t * 1e-9 * 1e9) != t  # the double alone misses it
    assert stamp("9223372036854775807.png", "1.5") == 2**63 - 1
    assert stamp("9223372036854775808.png", "1.5") == 1_500_000_000  # beyond int64: the double
    assert stamp("frame_0042.png", "2.25") == 2_250_000_000
    assert stamp("42.png", "2.25") == 42


def test_the_first_frame_after_a_reset_or_a_new_map_logs_no_preintegration(hook_rule):
    """ORB-SLAM3 v1.0's ResetActiveMap, Reset and CreateMapInAtlas set Tracking::mLastFrame to a default
    Frame, whose mTimeStamp Frame's default constructor leaves uninitialised (Frame.cc, Tracking.cc), and
    the next frame constructed integrates the IMU from it: that frame, and that frame alone, is marked
    so that log_frame writes no preintegration; a loop closure clears nothing."""
    out = subprocess.run([str(hook_rule), "--cleared", "ffrffnflfaffrrff"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    # frames:          f f | r f f | n f | l f | a f f | r r f f
    assert out.stdout.strip() == "00" + "10" + "1" + "0" + "10" + "10"
