"""jsve_keypoints.hpp: the keypoint side-file writer, compiled and read back by jsve.io.read_keypoints,
and Algorithm 1 as ORB-SLAM3's hook runs it, against jsve.masks.dynamic_keypoints.

tests/cpp/write_keypoints.cpp writes a side file from float bits (both number formatters of the
header); tests/cpp/mask_keypoints.cpp runs the header's Algorithm 1 and the hook's in-place drop of
keypoints and descriptor rows (jsve_orbslam3_hook.hpp without ORB-SLAM3) on random instance maps.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from test_frontend import CPP, CXX, STRICT, VARIANTS, build, compile_strictly, needs_cxx  # noqa: F401 - build: the fixture

import jsve.frontend
from jsve.io import LogIncompleteError, keypoints_path, read_keypoints
from jsve.masks import dynamic_keypoints
from jsve.masks._masks import DYNAMIC_CLASSES

HOOK_DIR = Path(jsve.frontend.__file__).resolve().parent / "orbslam3"


def _awkward_floats(rng, n: int) -> np.ndarray:
    """float32 coordinates: random pixels and values whose text needs all nine digits or an exponent."""
    special = np.float32([0.0, -0.0, 0.5, -0.5, 1e-7, 2.9999998, 751.99994, 0.1, 1.1920929e-07, 3e5])
    values = rng.uniform(-5.0, 760.0, n).astype(np.float32)
    values[: len(special)] = special
    return values


@needs_cxx
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_side_file_written_in_cpp_reads_back_bit_for_bit(build, tmp_path, variant):  # noqa: F811
    rng = np.random.default_rng(7)
    n = 400
    xy = np.stack([_awkward_floats(rng, n) for _ in range(4)], axis=1)  # x, y, ux, uy
    t_ns = 1403715274312143104 + 50_000_000 * np.sort(rng.integers(0, 30, n))
    octave = rng.integers(0, 8, n)
    inlier = rng.integers(0, 2, n)
    rows = "".join(
        f"{t} {' '.join(str(b) for b in bits)} {o} {i}\n"
        for t, bits, o, i in zip(t_ns, xy.view(np.uint32), octave, inlier, strict=True)
    )
    out = tmp_path / "run_003.keypoints.csv"
    refused = tmp_path / "refused"
    refused.mkdir()
    exe = build("write_keypoints.cpp", variant)
    done = subprocess.run([str(exe), str(out), str(refused)], input=rows, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    kp = read_keypoints(out)
    assert kp.meta == {
        "sequence": "V101", "run": 3, "disturbance": "blur", "level": 20.0, "image_size": [752, 480],
        "image_bounds": [-1.5, 760.25, 0.0, 481.0], "frontend": "test",
    }  # fmt: skip
    frame = kp.keypoints
    np.testing.assert_array_equal(frame["t_ns"], t_ns)
    np.testing.assert_array_equal(frame["octave"], octave)
    np.testing.assert_array_equal(frame["inlier"], inlier)
    read = frame[["x", "y", "ux", "uy"]].to_numpy().astype(np.float32)
    np.testing.assert_array_equal(read.view(np.uint32), xy.view(np.uint32))  # -0.0 included
    # floats keep a '.' or an exponent, as the log's float columns do
    first = out.read_text().splitlines()[2].split(",")
    assert all(("." in v or "e" in v) for v in first[1:5]), first


@needs_cxx
def test_the_writer_refuses_bad_rows_and_metadata_and_leaves_a_partial_file(build, tmp_path):  # noqa: F811
    refused = tmp_path / "refused"
    refused.mkdir()
    done = subprocess.run(
        [str(build("write_keypoints.cpp")), str(tmp_path / "ok.csv"), str(refused)],
        input="",
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    paths = [line.split()[1:] for line in lines if line.startswith("path ")]
    assert paths and all(side == str(keypoints_path(log)) for log, side in paths)
    status = dict(line.split(" ", 1) for line in lines if not line.startswith("path "))
    for name, reason in (("nan_x", "non-finite value"), ("negative_octave", "value out of range"),
                         ("stamp_back", "non-increasing stamp")):  # fmt: skip
        assert status[name] == reason
        # a rejected row fails the writer: nothing more is written and the file stays `.partial`
        assert status[f"{name}_then_write"] == status[f"{name}_then_close"] == "writer failed earlier"
        partial = refused / f"{name}.keypoints.csv.partial"
        assert partial.is_file() and not (refused / f"{name}.keypoints.csv").exists()
        with pytest.raises(LogIncompleteError):
            read_keypoints(partial)
        assert partial.read_text().count("\n") == 3  # line 1, header, the good row
    assert status["no_sequence"] == status["bad_bounds"] == status["bad_size"] == "bad metadata"
    assert not (refused / "x.csv.partial").exists()  # bad metadata creates no file
    assert status["empty"] == "ok" and len(read_keypoints(refused / "empty.keypoints.csv").keypoints) == 0
    assert status["exists"] == "file exists" and status["overwrite"] == "ok"
    assert status["thrown"] == "non-finite value"  # OnError::kThrow, the default


@needs_cxx
@pytest.mark.parametrize("standard", ["c++17", "c++20"])
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_the_header_compiles_warning_free_under_strict_flags(tmp_path, variant, standard):
    done = compile_strictly(CPP / "write_keypoints.cpp", tmp_path / "k.o", standard, variant)
    assert done.returncode == 0 and done.stderr == "", done.stderr


@pytest.fixture(scope="module")
def mask_keypoints(tmp_path_factory):
    if CXX is None:
        pytest.skip("no C++ compiler (g++, c++ or clang++) on PATH")
    exe = tmp_path_factory.mktemp("mask") / "mask_keypoints"
    strict = [*STRICT, "-Wconversion", "-Wshadow"]
    cmd = [CXX, "-std=c++17", "-O1", *strict, f"-I{jsve.frontend.get_include()}", f"-I{HOOK_DIR}"]
    done = subprocess.run(
        [*cmd, str(CPP / "mask_keypoints.cpp"), "-o", str(exe)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    return exe


def _keypoints_on_borders(rng, width: int, height: int, n: int) -> np.ndarray:
    """float32 (x, y): uniform over the image and a margin, plus the border cases of docs/masks.md."""
    xy = np.stack([rng.uniform(-3, width + 3, n), rng.uniform(-3, height + 3, n)], axis=1).astype(np.float32)
    edges_x = [-0.5, width - 0.5, -1.01, -1.0, -2.0, -2.5, 0.0, width - 1.0, width, width + 0.5, 1e30, -1e30]
    edges_y = [
        -0.5,
        height - 0.5,
        -1.01,
        -1.0,
        -2.0,
        -2.5,
        0.0,
        height - 1.0,
        height,
        height + 0.5,
        1e30,
        -1e30,
    ]
    grid = np.array([(x, y) for x in edges_x for y in edges_y], np.float32)
    integers = rng.integers(-2, max(width, height) + 2, (40, 2)).astype(np.float32)
    return np.concatenate([grid, integers, xy])


@needs_cxx
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_algorithm_1_in_the_hook_is_jsves(mask_keypoints, seed):
    """Random instance maps (cars, pedestrians, background, ignore regions, other classes) and keypoints
    inside, on and beyond every border, in the mask's image or (seeds 2, 3) in that image resized as
    ORB-SLAM3 resizes its input: the C++ decision equals jsve.masks.dynamic_keypoints on the mask
    PngMasks reads from the same map (classes 1, 2) at the keypoints' coordinates in the mask's image,
    and the hook's in-place drop keeps exactly the others, in order, each with its own descriptor row."""
    rng = np.random.default_rng(seed)
    width, height = int(rng.integers(1, 40)), int(rng.integers(1, 30))
    resized = (width, height) if seed < 2 else (int(rng.integers(1, 50)), int(rng.integers(1, 40)))
    ids = np.array([0, 0, 0, 1001, 1002, 2001, 2999, 10000, 3001, 999, 1999])
    instance = rng.choice(ids, (height, width)).astype(np.uint16)
    xy = _keypoints_on_borders(rng, *resized, 300)
    text = f"{width} {height} {resized[0]} {resized[1]}\n"
    text += "\n".join(" ".join(map(str, row)) for row in instance) + "\n"
    text += f"{len(xy)}\n" + "".join(f"{float(x).hex()} {float(y).hex()}\n" for x, y in xy)
    done = subprocess.run([str(mask_keypoints)], input=text, capture_output=True, text=True, check=True)
    *rows, kept, aligned = done.stdout.splitlines()
    hook = np.array([row.split()[0] == "1" for row in rows])
    source = np.array([[float.fromhex(v) for v in row.split()[1:]] for row in rows], np.float32)
    # cv::resize's geometry in float64, rounded to float (the identity when the sizes agree)
    scale = np.array([width / resized[0], height / resized[1]])
    expected_source = np.where(
        scale == 1.0, xy, ((xy.astype(np.float64) + 0.5) * scale - 0.5).astype(np.float32)
    )
    np.testing.assert_array_equal(source, expected_source)
    mask = (instance != 0) & np.isin(instance.astype(np.int64) // 1000, DYNAMIC_CLASSES)
    expected = np.asarray(dynamic_keypoints(jnp.asarray(mask), jnp.asarray(source), jnp.ones(len(xy), bool)))
    np.testing.assert_array_equal(hook, expected)
    assert 0 < expected.sum() < len(xy)  # both outcomes occur
    assert [int(k) for k in kept.split()[1:]] == np.flatnonzero(~expected).tolist()
    assert aligned == "aligned 1"
