"""`jsve frontend build`: ORB-SLAM3 v1.0 with jsve's hook, and jsve's driver program.

The user's ORB-SLAM3 (a clone or the v1.0 archive) is never modified: its sources are copied into
BUILD/ORB_SLAM3 (only files whose bytes differ are rewritten, so `make` recompiles only what changed),
and the copy is patched by anchored edits that fail loudly when an anchor is not found exactly once:
  * CMakeLists.txt: C++17 instead of C++11 (Pangolin 0.9 and GCC 12 need it); the examples and the
    in-tree g2o target are dropped (jsve builds its own driver, and g2o on its own as build.sh does);
  * src/LoopClosing.cc: `mnFullBAIdx++` on a bool (ill-formed in C++17) becomes `= true`, its C++14 meaning;
  * src/Tracking.cc: the hook (jsve/frontend/orbslam3/jsve_orbslam3_hook.hpp): one include and six calls;
  * src/Frame.cc: the hook header and, in the monocular constructor right after ExtractORB, the call that
    drops the keypoints on dynamic objects when the driver runs with masks (jsve_keypoints.hpp's
    Algorithm 1), before ORB-SLAM3 counts, undistorts or grids them;
  * src/Map.cc, src/LocalMapping.cc: the hook header and calls where ORB-SLAM3 re-expresses a map
    without a new id (ApplyScaledRotation; IMU initialisation and scale refinement with their inertial
    BA): the log's world_* columns;
  * src/LocalMapping.cc, src/LoopClosing.cc: the lockstep gates (jsve_orbslam3_lockstep.hpp): a park
    at the top of each Run() loop, a skipped sleep at its end and, in RunGlobalBundleAdjustment, a
    wait for both workers to park; all return at once unless the driver runs in lockstep;
    src/TwoViewReconstruction.cc: in lockstep the homography and fundamental-matrix RANSACs run in
    the calling thread, one after the other, instead of in two threads (threads that allocate at once
    make the heap's later addresses, by which ORB-SLAM3 orders keyframes and points, differ by run).
Then Pangolin (when not installed), DBoW2, g2o, the library and the driver are built with CMake in
BUILD/build/*. Layout of BUILD:

    ORB_SLAM3/            patched copy (lib/libORB_SLAM3.so and Thirdparty/*/lib after the build)
    build/{DBoW2,g2o,orbslam3,pangolin,driver}/   CMake build folders (kept: a re-run is incremental)
    pangolin/             Pangolin installed here when jsve built it
    bin/jsve_orbslam3     the driver (jsve/frontend/orbslam3/jsve_orbslam3.cc)
    build.log             every command and its output; build.json: what was built, from what, how long
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from jsve.frontend import get_include

HOOK_DIR = Path(__file__).resolve().parent / "orbslam3"
"""jsve's own C++ for ORB-SLAM3: the hook header, the driver and its CMakeLists.txt."""

SKIPPED = {".git", "Examples", "Examples_old", "Vocabulary", "lib", "build", "evaluation"}
"""Top-level entries of an ORB-SLAM3 tree that the build does not need (or that are build outputs)."""


_JSVE_HEADERS = tuple(Path(get_include()) / h for h in ("jsve_log.hpp", "jsve_keypoints.hpp"))
"""jsve's standard-library headers the hook includes (the log and keypoint writers)."""


class BuildError(RuntimeError):
    """A build step failed; the message names the step and, for a failed command, the log file."""


@dataclasses.dataclass(frozen=True)
class Edit:
    """Replace `anchor` (which must occur exactly once in `path`) by `replacement`."""

    path: str
    anchor: str
    replacement: str


HOOK_TAG = "  // jsve hook"
_SCALE_REFINED = (
    "    // To perform pose-inertial opt w.r.t. last keyframe\n"
    "    mpCurrentKeyFrame->GetMap()->IncreaseChangeIndex();\n"
)  # the end of LocalMapping::ScaleRefinement

_MONOCULAR_EXTRACTION = (
    "    ExtractORB(0,imGray,0,1000);\n"
    "#ifdef REGISTER_TIMES\n"
    "    std::chrono::steady_clock::time_point time_EndExtORB = std::chrono::steady_clock::now();\n"
    "\n"
    "    mTimeORB_Ext = std::chrono::duration_cast<std::chrono::duration<double,std::milli> >"
    "(time_EndExtORB - time_StartExtORB).count();\n"
    "#endif\n"
    "\n"
    "\n"
    "    N = mvKeys.size();\n"
)  # Frame's monocular constructor (MONOCULAR and IMU_MONOCULAR): the extraction, then N

_INITIALISER_THREADS = (
    "        thread threadH(&TwoViewReconstruction::FindHomography,this,"
    "ref(vbMatchesInliersH), ref(SH), ref(H));\n"
    "        thread threadF(&TwoViewReconstruction::FindFundamental,this,"
    "ref(vbMatchesInliersF), ref(SF), ref(F));\n"
    "\n"
    "        // Wait until both threads have finished\n"
    "        threadH.join();\n"
    "        threadF.join();\n"
)  # TwoViewReconstruction::Reconstruct runs its homography and fundamental-matrix RANSACs in two threads
_LOCAL_MAPPING_LOOP_TOP = (
    "    while(1)\n    {\n"
    "        // Tracking will see that Local Mapping is busy\n        SetAcceptKeyFrames(false);\n"
)  # the top of LocalMapping::Run's loop
_LOOP_CLOSING_LOOP_TOP = "    mbFinished =false;\n\n    while(1)\n    {\n"  # LoopClosing::Run's loop
_GLOBAL_BA_START = (
    "void LoopClosing::RunGlobalBundleAdjustment(Map* pActiveMap, unsigned long nLoopKF)\n{  \n"
)
_LOCAL_MAPPING_LOOP_END = (  # the end of LocalMapping::Run's loop
    "        if(CheckFinish())\n            break;\n\n        usleep(3000);\n    }\n\n    SetFinish();\n"
)
_LOOP_CLOSING_LOOP_END = (
    "        if(CheckFinish()){\n            break;\n        }\n\n"
    "        usleep(5000);\n    }\n\n    SetFinish();\n"
)  # the end of LoopClosing::Run's loop

EDITS = (
    Edit("CMakeLists.txt", '"${CMAKE_CXX_FLAGS} -std=c++11")', '"${CMAKE_CXX_FLAGS} -std=c++17")'),
    Edit("CMakeLists.txt", '"${CMAKE_CXX_FLAGS} -std=c++0x")', '"${CMAKE_CXX_FLAGS} -std=c++17")'),
    Edit("CMakeLists.txt", "add_subdirectory(Thirdparty/g2o)\n", ""),
    Edit(
        "src/Tracking.cc",
        '#include "GeometricTools.h"\n',
        '#include "GeometricTools.h"\n#define JSVE_HOOK_IMPLEMENTATION' + HOOK_TAG
        + '\n#include "jsve_orbslam3_hook.hpp"' + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Tracking.cc",
        "    if(nToMatch>0)\n    {\n        ORBmatcher matcher(0.8);\n",
        "    JSVE_HOOK_FRUSTUM(nToMatch);"
        + HOOK_TAG
        + "\n    if(nToMatch>0)\n    {\n        ORBmatcher matcher(0.8);\n",
    ),
    Edit(
        "src/Tracking.cc",
        "    mpLocalMapper->mnMatchesInliers=mnMatchesInliers;\n",
        "    mpLocalMapper->mnMatchesInliers=mnMatchesInliers;\n"
        + "    JSVE_HOOK_INLIERS(mnMatchesInliers);"
        + HOOK_TAG
        + "\n    JSVE_HOOK_DECIDE();"
        + HOOK_TAG
        + "\n",
    ),
    Edit(
        "src/Tracking.cc",
        "    mTrackedFr++;\n",
        "    mTrackedFr++;\n    JSVE_HOOK_SAVE_PREDICTION();" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Tracking.cc",
        "    lastID = mCurrentFrame.mnId;\n    Track();\n",
        "    lastID = mCurrentFrame.mnId;\n    JSVE_HOOK_BEGIN_FRAME();" + HOOK_TAG
        + "\n    Track();\n    JSVE_HOOK_LOG_FRAME();" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Frame.cc",
        '#include "Frame.h"\n',
        '#include "Frame.h"\n#include "jsve_orbslam3_hook.hpp"' + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Frame.cc",
        _MONOCULAR_EXTRACTION,
        _MONOCULAR_EXTRACTION.replace(
            "    N = mvKeys.size();\n",
            "    JSVE_HOOK_MASK_KEYPOINTS();" + HOOK_TAG + "\n    N = mvKeys.size();\n",
        ),
    ),
    Edit(
        "src/Map.cc",
        '#include "Map.h"\n',
        '#include "Map.h"\n#include "jsve_orbslam3_hook.hpp"' + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Map.cc",
        "        pMP->UpdateNormalAndDepth();\n    }\n    mnMapChange++;\n}\n",
        "        pMP->UpdateNormalAndDepth();\n    }\n    mnMapChange++;\n"
        + "    JSVE_HOOK_WORLD_CHANGE(mnId, T, s);" + HOOK_TAG + "\n}\n",
    ),
    Edit(
        "src/LocalMapping.cc",
        '#include "LocalMapping.h"\n',
        '#include "LocalMapping.h"\n#include "jsve_orbslam3_hook.hpp"' + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LocalMapping.cc",
        "void LocalMapping::InitializeIMU(float priorG, float priorA, bool bFIBA)\n{\n",
        "void LocalMapping::InitializeIMU(float priorG, float priorA, bool bFIBA)\n{\n"
        + "    JSVE_HOOK_MAP_SNAPSHOT(mpAtlas->GetCurrentMap());" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LocalMapping.cc",
        "    bInitializing = false;\n\n    mpCurrentKeyFrame->GetMap()->IncreaseChangeIndex();\n",
        "    bInitializing = false;\n\n    mpCurrentKeyFrame->GetMap()->IncreaseChangeIndex();\n"
        + "    JSVE_HOOK_MAP_CHANGED(mpCurrentKeyFrame->GetMap());" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LocalMapping.cc",
        "void LocalMapping::ScaleRefinement()\n{\n",
        "void LocalMapping::ScaleRefinement()\n{\n"
        + "    JSVE_HOOK_MAP_SNAPSHOT(mpAtlas->GetCurrentMap());" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LocalMapping.cc",
        _SCALE_REFINED,
        _SCALE_REFINED + "    JSVE_HOOK_MAP_CHANGED(mpCurrentKeyFrame->GetMap());" + HOOK_TAG + "\n",
    ),
    # Format v3: the events (jsve::Event) at their places.
    Edit(
        "src/Tracking.cc",
        "    mlbLost = lbLost;\n",
        "    mlbLost = lbLost;\n    JSVE_HOOK_EVENT(kEventReset);" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Tracking.cc",
        "void Tracking::Reset(bool bLocMap)\n{\n",
        "void Tracking::Reset(bool bLocMap)\n{\n    JSVE_HOOK_RESET_ALL();" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Tracking.cc",
        "void Tracking::CreateMapInAtlas()\n{\n",
        "void Tracking::CreateMapInAtlas()\n{\n    JSVE_HOOK_EVENT(kEventNewMap);" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/Map.cc",
        "    mbImuInitialized = true;\n",
        "    if (!mbImuInitialized) JSVE_HOOK_EVENT(kEventImuInit);" + HOOK_TAG
        + "\n    mbImuInitialized = true;\n",
    ),
    Edit(
        "src/Map.cc",
        "    mbIMU_BA1 = true;\n",
        "    if (!mbIMU_BA1) JSVE_HOOK_EVENT(kEventBa1);" + HOOK_TAG + "\n    mbIMU_BA1 = true;\n",
    ),
    Edit(
        "src/Map.cc",
        "    mbIMU_BA2 = true;\n",
        "    if (!mbIMU_BA2) JSVE_HOOK_EVENT(kEventBa2);" + HOOK_TAG + "\n    mbIMU_BA2 = true;\n",
    ),
    Edit(
        "src/LoopClosing.cc",
        '#include "LoopClosing.h"\n',
        '#include "LoopClosing.h"\n#include "jsve_orbslam3_hook.hpp"' + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LoopClosing.cc",
        "void LoopClosing::CorrectLoop()\n{\n",
        "void LoopClosing::CorrectLoop()\n{\n    JSVE_HOOK_EVENT(kEventLoop);" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LoopClosing.cc",
        "void LoopClosing::MergeLocal()\n{\n",
        "void LoopClosing::MergeLocal()\n{\n    JSVE_HOOK_EVENT(kEventMerge);" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LoopClosing.cc",
        "void LoopClosing::MergeLocal2()\n{\n",
        "void LoopClosing::MergeLocal2()\n{\n    JSVE_HOOK_EVENT(kEventMerge);" + HOOK_TAG + "\n",
    ),
    # Lockstep (jsve_orbslam3_lockstep.hpp): each worker parks at the top of its Run() loop and skips
    # the loop's sleep; the global BA starts once both are parked; the monocular initialiser's two
    # RANSACs run in the tracking thread, one after the other.
    Edit(
        "src/LocalMapping.cc",
        _LOCAL_MAPPING_LOOP_TOP,
        _LOCAL_MAPPING_LOOP_TOP.replace(
            "    {\n", "    {\n        JSVE_LOCKSTEP_PARK_LOCAL_MAPPING();" + HOOK_TAG + "\n", 1
        ),
    ),
    Edit(
        "src/LocalMapping.cc",
        _LOCAL_MAPPING_LOOP_END,
        _LOCAL_MAPPING_LOOP_END.replace(
            "        usleep(3000);\n",
            "        JSVE_LOCKSTEP_SKIP_SLEEP();" + HOOK_TAG + "\n        usleep(3000);\n",
        ),
    ),
    Edit(
        "src/LoopClosing.cc",
        _LOOP_CLOSING_LOOP_TOP,
        _LOOP_CLOSING_LOOP_TOP + "        JSVE_LOCKSTEP_PARK_LOOP_CLOSING();" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/LoopClosing.cc",
        _LOOP_CLOSING_LOOP_END,
        _LOOP_CLOSING_LOOP_END.replace(
            "        usleep(5000);\n",
            "        JSVE_LOCKSTEP_SKIP_SLEEP();" + HOOK_TAG + "\n        usleep(5000);\n",
        ),
    ),
    Edit(
        "src/LoopClosing.cc",
        _GLOBAL_BA_START,
        _GLOBAL_BA_START + "    ::jsve_hook::wait_workers_parked();" + HOOK_TAG + "\n",
    ),
    Edit(
        "src/TwoViewReconstruction.cc",
        '#include "TwoViewReconstruction.h"\n',
        '#include "TwoViewReconstruction.h"\n#include "jsve_orbslam3_lockstep.hpp"' + HOOK_TAG + "\n",
    ),
    Edit(
        "src/TwoViewReconstruction.cc",
        _INITIALISER_THREADS,
        "        if (::jsve_hook::lockstep_on()) {" + HOOK_TAG + ": the same two calls, in this thread\n"
        "            FindHomography(vbMatchesInliersH, SH, H);" + HOOK_TAG + "\n"
        "            FindFundamental(vbMatchesInliersF, SF, F);" + HOOK_TAG + "\n"
        "        } else {" + HOOK_TAG + "\n" + _INITIALISER_THREADS + "        }" + HOOK_TAG + "\n",
    ),
)  # fmt: skip
"""The anchored edits, in order. Anchors are ORB-SLAM3 v1.0 (@4452a3c) lines; see docs/frontend.md."""

REPLACE_ALL = (
    (
        "src/LoopClosing.cc",
        "mnFullBAIdx++;",
        "mnFullBAIdx = true;  // jsve build: bool++ (C++14: sets true) is ill-formed in C++17",
    ),
)
"""Edits applied at every occurrence (at least one): (path, old, new)."""

TRUNCATE = (("CMakeLists.txt", "# Build examples"),)
"""(path, marker): the file ends before the marker (ORB-SLAM3's example programs are not built)."""


def patch_text(path: str, text: str, source: str = "ORB-SLAM3") -> str:
    """`text` of the file `path` (relative to the tree) with jsve's edits applied.

    Raises:
        BuildError naming the file and the anchor when an anchor is not found exactly once (not
        ORB-SLAM3 v1.0, or already patched).
    """
    for name, marker in TRUNCATE:
        if name == path:
            if text.count(marker) != 1:
                raise BuildError(
                    f"{source}/{path}: {marker!r} found {text.count(marker)} times, expected once"
                )
            text = text[: text.index(marker)]
    for edit in EDITS:
        if edit.path == path:
            n = text.count(edit.anchor)
            if n != 1:
                raise BuildError(
                    f"{source}/{path}: anchor {edit.anchor.strip()!r} found {n} times, expected once "
                    "(jsve's hook is written for ORB-SLAM3 v1.0, @4452a3c)"
                )
            text = text.replace(edit.anchor, edit.replacement)
    for name, old, new in REPLACE_ALL:
        if name == path:
            if old not in text:
                raise BuildError(f"{source}/{path}: {old!r} not found (ORB-SLAM3 v1.0 has it)")
            text = text.replace(old, new)
    return text


PATCHED = sorted({e.path for e in EDITS} | {p for p, *_ in REPLACE_ALL} | {p for p, _ in TRUNCATE})
"""Files of the tree that jsve edits."""


def _write_if_changed(path: Path, data: bytes) -> bool:
    """Write `data` to `path` unless it already holds exactly that (keeps mtimes: make rebuilds nothing)."""
    if path.is_file() and path.read_bytes() == data:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".jsve-tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return True


def _source_files(root: Path) -> Iterator[Path]:
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if rel.parts[0] in SKIPPED or not path.is_file():
            continue
        # Thirdparty build outputs (a user's tree may have run build.sh)
        if rel.parts[0] == "Thirdparty" and len(rel.parts) > 2 and rel.parts[2] in ("build", "lib"):
            continue
        yield path


def stage_source(orbslam3: Path, dest: Path) -> list[str]:
    """Copy the ORB-SLAM3 tree `orbslam3` into `dest`, patched, with jsve's headers in dest/include.

    Returns:
        Relative paths that were (re)written (empty when `dest` was already up to date).
    Raises:
        BuildError when `orbslam3` does not look like ORB-SLAM3 or an anchor is missing.
    """
    if not (orbslam3 / "src" / "Tracking.cc").is_file() or not (orbslam3 / "CMakeLists.txt").is_file():
        raise BuildError(f"{orbslam3}: not an ORB-SLAM3 source tree (no src/Tracking.cc or CMakeLists.txt)")
    changed = []
    for path in _source_files(orbslam3):
        rel = path.relative_to(orbslam3).as_posix()
        data = path.read_bytes()
        if rel in PATCHED:
            data = patch_text(rel, data.decode("utf-8"), source=str(orbslam3)).encode("utf-8")
        if _write_if_changed(dest / rel, data):
            changed.append(rel)
    headers = ("jsve_orbslam3_hook.hpp", "jsve_orbslam3_lockstep.hpp")
    for header in (*(HOOK_DIR / h for h in headers), *_JSVE_HEADERS):
        if _write_if_changed(dest / "include" / header.name, header.read_bytes()):
            changed.append(f"include/{header.name}")
    return changed


def _unpack(archive: Path, into: Path) -> Path:
    """Extract a .tar.gz of ORB-SLAM3 (or Pangolin) and return the tree's root (the one top folder)."""
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    entries = [p for p in into.iterdir()]
    return entries[0] if len(entries) == 1 and entries[0].is_dir() else into


class _Runner:
    """Runs build commands, appending each command and its output to a log, showing make's progress."""

    def __init__(self, log: Path, progress: bool):
        self.log, self.progress = log, progress

    def __call__(self, stage: str, cmd: list[str]) -> None:
        with self.log.open("a") as log:
            log.write(f"\n$ {' '.join(cmd)}\n")
            log.flush()
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            assert proc.stdout is not None
            last = None
            for line in proc.stdout:
                log.write(line)
                m = re.match(r"\[\s*(\d+)%\]", line)
                if self.progress and m and m.group(1) != last:
                    last = m.group(1)
                    print(f"\r{stage}: {last:>3}%", end="", file=sys.stderr, flush=True)
            code = proc.wait()
        if self.progress and last is not None:
            print(file=sys.stderr)
        if code != 0:
            raise BuildError(f"{stage} failed (exit {code}): see {self.log}")


def _cmake(
    run: _Runner, stage: str, source: Path, build: Path, jobs: int, *defs: str, target: str = ""
) -> None:
    build.mkdir(parents=True, exist_ok=True)
    run(
        f"{stage} (configure)",
        ["cmake", "-S", str(source), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release", *defs],
    )
    run(stage, ["cmake", "--build", str(build), "-j", str(jobs), *(["--target", target] if target else [])])


def _hash_files(paths: list[Path]) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode() + b"\0" + p.read_bytes())
    return h.hexdigest()


def build(
    orbslam3: Path,
    out: Path,
    *,
    pangolin: Path | None = None,
    pangolin_src: Path | None = None,
    jobs: int = 2,
    progress: bool = True,
) -> Path:
    """Build ORB-SLAM3 v1.0 with jsve's hook and the driver into `out`; returns the driver's path.

    Arguments:
        orbslam3: an ORB-SLAM3 v1.0 source tree or its .tar.gz archive (never modified).
        out: the build folder (layout in the module docstring); a re-run rebuilds only what changed.
        pangolin: prefix of an installed Pangolin (holding lib/cmake/Pangolin); default: one jsve built
            in out/pangolin, else CMake's search.
        pangolin_src: Pangolin's sources (folder or .tar.gz) to build into out/pangolin when none is
            installed.
        jobs: parallel compile jobs (ORB-SLAM3's Optimizer.cc alone needs ~4 GB).
    Raises:
        BuildError naming the failed step (and the log holding the compiler's output).
    """
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    run = _Runner(out / "build.log", progress)
    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) if progress else (lambda msg: None)
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        tree = _unpack(orbslam3, Path(tmp)) if orbslam3.is_file() else orbslam3.resolve()
        changed = stage_source(tree, out / "ORB_SLAM3")
    say(f"jsve frontend build: {len(changed)} files of ORB-SLAM3 (re)staged in {out / 'ORB_SLAM3'}")
    pangolin_dir = _pangolin(run, out, pangolin, pangolin_src, jobs, say)
    src = out / "ORB_SLAM3"
    for lib in ("DBoW2", "g2o"):
        _cmake(run, lib, src / "Thirdparty" / lib, out / "build" / lib, jobs)
    defs = [f"-DPangolin_DIR={pangolin_dir}"] if pangolin_dir else []
    _cmake(run, "ORB-SLAM3", src, out / "build" / "orbslam3", jobs, *defs, target="ORB_SLAM3")
    _cmake(
        run, "driver", HOOK_DIR, out / "build" / "driver", jobs, *defs,
        f"-DORB_SLAM3_DIR={src}", f"-DJSVE_INCLUDE={get_include()}",
    )  # fmt: skip
    driver = out / "bin" / "jsve_orbslam3"
    driver.parent.mkdir(exist_ok=True)
    # copy, then rename: a driver that is running (`jsve frontend run`) keeps its file
    staged = driver.with_name(driver.name + ".jsve-tmp")
    shutil.copy2(out / "build" / "driver" / "bin" / "jsve_orbslam3", staged)
    staged.replace(driver)
    record = {
        "orbslam3": str(orbslam3),
        "hook_sha256": _hash_files(sorted(HOOK_DIR.iterdir()) + list(_JSVE_HEADERS)),
        "restaged": changed,
        "pangolin_dir": str(pangolin_dir) if pangolin_dir else None,
        "driver": str(driver),
        "seconds": round(time.monotonic() - started, 1),
    }
    (out / "build.json").write_text(json.dumps(record, indent=2) + "\n")
    say(f"jsve frontend build: {driver} ({record['seconds']} s)")
    return driver


def _pangolin(
    run: _Runner, out: Path, prefix: Path | None, source: Path | None, jobs: int, say
) -> Path | None:
    """Pangolin's CMake folder: the given prefix's, or jsve's own install (built from `source` when
    missing); None lets CMake search the system."""
    if prefix is not None:
        config = prefix.resolve() / "lib" / "cmake" / "Pangolin"
        if not (config / "PangolinConfig.cmake").is_file():
            raise BuildError(f"--pangolin {prefix}: no lib/cmake/Pangolin/PangolinConfig.cmake there")
        return config
    own = out / "pangolin" / "lib" / "cmake" / "Pangolin"
    if (own / "PangolinConfig.cmake").is_file():
        return own
    if source is None:
        return None
    say("jsve frontend build: building Pangolin (about 5 min at -j2)")
    # An archive is unpacked to a fixed place: its CMake build folder remembers the source folder.
    unpacked = out / "build" / "pangolin-src"
    if source.is_file() and not unpacked.is_dir():
        with tempfile.TemporaryDirectory(dir=out) as tmp:
            shutil.move(_unpack(source, Path(tmp)), unpacked)
    tree = unpacked if source.is_file() else source.resolve()
    flags = ["-DBUILD_EXAMPLES=OFF", "-DBUILD_TOOLS=OFF", "-DBUILD_PANGOLIN_PYTHON=OFF", "-DBUILD_TESTS=OFF"]
    _cmake(
        run,
        "Pangolin",
        tree,
        out / "build" / "pangolin",
        jobs,
        *flags,
        f"-DCMAKE_INSTALL_PREFIX={out / 'pangolin'}",
    )
    run("Pangolin (install)", ["cmake", "--install", str(out / "build" / "pangolin")])
    return own
