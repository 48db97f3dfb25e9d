"""jsve frontend build's source staging: the hook's anchored edits on ORB-SLAM3 v1.0 (the archive in
../shared/third_party when present), loud failures on other sources, and idempotence (no rewrite, so
`make` rebuilds nothing). The compile itself is opt-in: .ci/frontend-smoke."""

from __future__ import annotations

import tarfile
from pathlib import Path

import pytest

from jsve.frontend._build import EDITS, HOOK_TAG, BuildError, patch_text, stage_source

ARCHIVE = (
    Path(__file__).resolve().parents[1].parent / "shared" / "third_party" / "ORB_SLAM3-v1.0-4452a3c.tar.gz"
)


@pytest.fixture(scope="module")
def orbslam3(tmp_path_factory) -> Path:
    if not ARCHIVE.is_file():
        pytest.skip(f"ORB-SLAM3 archive not found at {ARCHIVE}")
    root = tmp_path_factory.mktemp("orbslam3")
    with tarfile.open(ARCHIVE) as tar:
        tar.extractall(root, filter="data")
    (tree,) = root.iterdir()
    return tree


def test_hook_edits_apply_once_each_to_v1(orbslam3, tmp_path):
    changed = stage_source(orbslam3, tmp_path / "ORB_SLAM3")
    assert {
        "src/Tracking.cc",
        "CMakeLists.txt",
        "include/jsve_orbslam3_hook.hpp",
        "include/jsve_log.hpp",
    } <= set(changed)
    tracking = (tmp_path / "ORB_SLAM3" / "src" / "Tracking.cc").read_text()
    original = (orbslam3 / "src" / "Tracking.cc").read_text()
    # every edit adds exactly its tagged lines; nothing of ORB-SLAM3's is removed from Tracking.cc
    assert tracking.count(HOOK_TAG) == 11
    assert [line for line in tracking.splitlines() if HOOK_TAG not in line] == original.splitlines()
    order = [
        tracking.index(s) for s in ("JSVE_HOOK_BEGIN_FRAME();", "    Track();\n    JSVE_HOOK_LOG_FRAME();")
    ]
    assert order == sorted(order)
    cmake = (tmp_path / "ORB_SLAM3" / "CMakeLists.txt").read_text()
    assert "-std=c++17" in cmake and '-std=c++11")' not in cmake and "add_executable" not in cmake
    assert "mnFullBAIdx++" not in (tmp_path / "ORB_SLAM3" / "src" / "LoopClosing.cc").read_text()
    assert not (tmp_path / "ORB_SLAM3" / "Examples").exists()


def test_lockstep_gates_add_lines_and_keep_every_line_of_orbslam3(orbslam3, tmp_path):
    stage_source(orbslam3, tmp_path / "ORB_SLAM3")
    for name, gates in (
        ("src/LocalMapping.cc", ["JSVE_LOCKSTEP_PARK_LOCAL_MAPPING();", "SetAcceptKeyFrames(false);",
                                 "JSVE_LOCKSTEP_SKIP_SLEEP();", "usleep(3000);\n    }\n\n    SetFinish();"]),
        ("src/LoopClosing.cc", ["JSVE_LOCKSTEP_PARK_LOOP_CLOSING();", "if(CheckNewKeyFrames())",
                                "JSVE_LOCKSTEP_SKIP_SLEEP();", "usleep(5000);\n    }\n\n    SetFinish();",
                                "RunGlobalBundleAdjustment(Map* pActiveMap", "wait_workers_parked();"]),
        ("src/TwoViewReconstruction.cc", ["lockstep_on()", "FindFundamental(vbMatchesInliersF, SF, F);",
                                          "thread threadH("]),
    ):  # fmt: skip
        patched = (tmp_path / "ORB_SLAM3" / name).read_text()
        original = (orbslam3 / name).read_text()
        kept = [line for line in patched.splitlines() if HOOK_TAG not in line and "jsve build" not in line]
        assert kept == [line for line in original.splitlines() if "mnFullBAIdx++" not in line], name
        # each gate where it belongs: the park first in the loop, the skipped sleep right before it
        where = [patched.index(g) for g in gates]
        assert where == sorted(where), name
    assert (tmp_path / "ORB_SLAM3" / "include" / "jsve_orbslam3_lockstep.hpp").is_file()


def test_staging_twice_rewrites_nothing(orbslam3, tmp_path):
    stage_source(orbslam3, tmp_path / "t")
    mtimes = {p: p.stat().st_mtime_ns for p in (tmp_path / "t").rglob("*") if p.is_file()}
    assert stage_source(orbslam3, tmp_path / "t") == []
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "t").rglob("*") if p.is_file()} == mtimes


@pytest.mark.parametrize("edit", EDITS, ids=lambda e: f"{e.path}:{e.anchor.strip()[:30]}")
def test_a_missing_or_repeated_anchor_names_the_file_and_anchor(orbslam3, edit):
    """v1.0's file with one anchor removed, or doubled, is refused with the file and that anchor."""
    text = (orbslam3 / edit.path).read_text()
    with pytest.raises(BuildError, match=rf"tree/{edit.path}: anchor .* found 0 times"):
        patch_text(edit.path, text.replace(edit.anchor, ""), source="tree")
    with pytest.raises(BuildError, match=rf"tree/{edit.path}: anchor .* found 2 times"):
        patch_text(edit.path, text.replace(edit.anchor, edit.anchor + edit.anchor), source="tree")


def test_an_already_patched_file_is_refused(orbslam3):
    once = patch_text("src/Tracking.cc", (orbslam3 / "src" / "Tracking.cc").read_text())
    with pytest.raises(BuildError, match="found 0 times|found 2 times"):
        patch_text("src/Tracking.cc", once)


def test_not_an_orbslam3_tree(tmp_path):
    with pytest.raises(BuildError, match="not an ORB-SLAM3 source tree"):
        stage_source(tmp_path, tmp_path / "out")


def test_masks_drop_keypoints_in_the_monocular_frame_right_after_extraction(orbslam3, tmp_path):
    """The mask call sits in the one Frame constructor both MONOCULAR and IMU_MONOCULAR build their frames
    with (Tracking::GrabImageMonocular), after ExtractORB and before N, the undistortion and the grid;
    Frame.cc keeps every line of ORB-SLAM3's."""
    stage_source(orbslam3, tmp_path / "ORB_SLAM3")
    patched = (tmp_path / "ORB_SLAM3" / "src" / "Frame.cc").read_text()
    original = (orbslam3 / "src" / "Frame.cc").read_text()
    assert [line for line in patched.splitlines() if HOOK_TAG not in line] == original.splitlines()
    assert patched.count("JSVE_HOOK_MASK_KEYPOINTS();") == 1
    monocular = patched.index(
        "Frame::Frame(const cv::Mat &imGray, const double &timeStamp, ORBextractor* extractor,"
        "ORBVocabulary* voc, GeometricCamera* pCamera,"
    )
    steps = ["ExtractORB(0,imGray,0,1000);", "JSVE_HOOK_MASK_KEYPOINTS();", "N = mvKeys.size();",
             "UndistortKeyPoints();", "AssignFeaturesToGrid();"]  # fmt: skip
    where = [patched.index(s, monocular) for s in steps]
    assert where == sorted(where)
    assert where[-1] < patched.index("Frame::Frame(", monocular + 1)  # all within that constructor
    tracking = (orbslam3 / "src" / "Tracking.cc").read_text()
    grab = tracking[tracking.index("Sophus::SE3f Tracking::GrabImageMonocular") :]
    grab = grab[: grab.index("\n}\n")]
    # every frame of both monocular sensors comes from that constructor (its signature: image, stamp)
    assert grab.count("mCurrentFrame = Frame(mImGray,timestamp,") == 4
    assert (tmp_path / "ORB_SLAM3" / "include" / "jsve_keypoints.hpp").is_file()
