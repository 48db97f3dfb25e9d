"""Shared fixtures: the real data in ../shared/data (skipped when absent), float64 switching, and jsve's
own shape errors with jaxtyping's runtime checker (on for jsve.core through pyproject's addopts) off."""

from __future__ import annotations

import contextlib
import gc
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

SUITE_XLA_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_backend_optimization_level=0",
    "--xla_cpu_multi_thread_eigen=false",
    "--xla_cpu_parallel_codegen_split_count=1",
    "--xla_cpu_copy_insertion_use_region_analysis=false",
    "--xla_cpu_enable_concurrency_optimized_scheduler=false",
)
"""XLA's CPU compiler set for programs that run once: its classic fusion emitter, which compiles the
suite's small programs faster than the MLIR fusion emitters, no LLVM optimisation, Eigen's operations
on the calling thread (each pytest-xdist worker has a core; a pool of threads per worker only contends
with the other worker), each program's machine code emitted as one LLVM module rather than parts for
parallel code generation (one thread per worker gains nothing from the split), and the cheaper copy
insertion and instruction scheduling. Most of the suite's time is compiling; none of these changes what
a program computes, and nothing a test asserts depends on how fast compiled code runs (the figures:
docs/performance.md, "The test suite"). A flag the user's XLA_FLAGS already sets wins. XLA reads
XLA_FLAGS when its backend starts, after this module is imported."""


def _with_suite_xla_flags() -> None:
    """Add SUITE_XLA_FLAGS to XLA_FLAGS once per pytest run (its xdist workers inherit the result), after a
    child process shows that this jaxlib accepts them: XLA aborts on a flag it does not know, and a later
    jaxlib may drop these."""
    if os.environ.get("JSVE_TEST_XLA_FLAGS_SET"):
        return
    os.environ["JSVE_TEST_XLA_FLAGS_SET"] = "1"
    present = os.environ.get("XLA_FLAGS", "")
    added = [f for f in SUITE_XLA_FLAGS if f.split("=")[0] not in present]
    if not added:
        return
    flags = " ".join([present, *added]).strip()
    probe = subprocess.run(
        [sys.executable, "-c", "import jax; jax.jit(lambda x: x + 1)(1.0).block_until_ready()"],
        env={**os.environ, "XLA_FLAGS": flags},
        capture_output=True,
    )
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = flags
    else:
        warnings.warn(f"this jaxlib refuses {added}; the suite compiles with XLA's defaults", stacklevel=1)


_with_suite_xla_flags()

import jax  # noqa: E402
import jaxtyping  # noqa: E402
import pytest  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# The commands' persistent compilation cache (jsve._jax_cache) is the suite's own (below), or off: the
# suite neither writes into the user's cache folder nor reads executables compiled by another checkout.
# tests/test_jax_cache.py points it at folders of its own.
os.environ["JSVE_JAX_CACHE"] = "off"

SUITE_CACHE_ENV = "JSVE_TEST_JAX_CACHE"
"""A JAX compilation cache folder of this test run alone (a fresh temporary folder, deleted at its end),
shared by its pytest-xdist workers: a computation one worker compiled, the other loads, and a module that
compiles what an earlier one did (the in-memory caches are dropped after every module, below) loads it
too. The processes a test starts read and write it as well: the commands (`python -m jsve.cli ...`) as
their JSVE_JAX_CACHE, any other (a Dask worker, a process pool's worker) through JAX's own
JAX_COMPILATION_CACHE_DIR. Results are the same either way: the same executables. Set it to a folder to
keep one across runs, or to "off" to compile everything."""


def pytest_configure(config):
    if not hasattr(config, "workerinput") and SUITE_CACHE_ENV not in os.environ:
        # the controller (or a run without xdist): its workers start after this and inherit the folder
        config.suite_cache_made = os.environ[SUITE_CACHE_ENV] = tempfile.mkdtemp(prefix="jsve-tests-jax-")
    folder = os.environ.get(SUITE_CACHE_ENV, "off")
    if folder.strip().lower() not in ("", "0", "off", "false", "no", "none"):
        os.environ["JSVE_JAX_CACHE"] = folder
        os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
        os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
        os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_collection_finish(session):
    """Move what importing and collecting made (the modules, the test items: about 330,000 objects) to
    the garbage collector's permanent generation. They live to the end of the run; left tracked, every
    full collection walks them again: the automatic ones and jsve._memory.release_memory's between the
    stages of each fit."""
    gc.collect()
    gc.freeze()


def pytest_unconfigure(config):
    made = getattr(config, "suite_cache_made", None)
    if made:
        shutil.rmtree(made, ignore_errors=True)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the checkout; tests using it skip cleanly on a user's fresh clone."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_caches():
    """Drop JAX's compiled functions after each test module. The whole suite in one process compiles
    thousands of executables; kept to the end, the full run crashed inside XLA's CPU compiler
    (SIGSEGV / SIGABRT in backend_compile, tests/test_rules.py, two runs of .ci/run) although every
    half of the suite passed on its own. Nothing a test asserts depends on a warm cache."""
    yield
    jax.clear_caches()


@pytest.fixture
def x64():
    """Run a test in float64 (tolerances of 1e-6 and tighter need it)."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", previous)


@pytest.fixture
def unchecked():
    """A context without jaxtyping's runtime checker, for a test of jsve's own error for a wrong shape.

    pyproject's addopts check every annotation of jsve.core at test time; a call whose shapes contradict
    the annotations is then rejected by the checker (a TypeCheckError) before jsve's own check runs. Users
    run without the checker and get jsve's ValueError naming the argument; that is what such a test asserts:

        with unchecked(), pytest.raises(ValueError, match="ref_p has 9 frames"):
            align(est_p, ref_p[:9], mask, method="se3")
    """

    @contextlib.contextmanager
    def off():
        previous = jaxtyping.config.jaxtyping_disable
        jaxtyping.config.update("jaxtyping_disable", True)
        try:
            yield
        finally:
            jaxtyping.config.update("jaxtyping_disable", previous)

    return off


@pytest.fixture
def mixed_runs():
    """Three runs a LogBatch must hold together: 100, 130 and 65 frames; 20 and 10 fps; ground truth
    complete, 20 % missing and absent; gravity along -z and along -y (test_batch.py, test_batching.py)."""
    from logfactory import make_run

    return [
        make_run(100, seed=1, sequence="MH_04", disturbance="blur", level=15),
        make_run(130, seed=2, gt_missing=0.2, fps=10),
        make_run(65, seed=3, with_gt=False, gravity=[0.0, -9.81, 0.0]),
    ]


@pytest.fixture(scope="module")
def first_frames(shared_data):
    """The first six cam0 frames of the real EuRoC V1_01 (uint8 images), its Camera and their stamps
    (int64 ns), from ../shared/data/euroc/V1_01_first95 (test_orb.py, test_measure.py)."""
    from jsve.image import read_image, read_sequence

    sequence = read_sequence(shared_data / "euroc" / "V1_01_first95")
    return [read_image(p) for p in sequence.paths[:6]], sequence.camera, sequence.t_ns[:6]
