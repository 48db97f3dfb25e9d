// jsve's hook for ORB-SLAM3 v1.0: one format-v3 log row per frame (and the trailer at the end), written through jsve_log.hpp.
//
// `jsve frontend build` copies ORB-SLAM3, includes this header in src/Tracking.cc (with
// JSVE_HOOK_IMPLEMENTATION defined) and adds four one-line calls at anchored places
// (jsve/frontend/_build.py, docs/frontend.md section 4):
//   SearchLocalPoints  JSVE_HOOK_FRUSTUM(nToMatch)           the frustum count of this frame
//   TrackLocalMap      JSVE_HOOK_SAVE_PREDICTION() at its start; JSVE_HOOK_INLIERS(mnMatchesInliers)
//                      and JSVE_HOOK_DECIDE() after the count, before ORB-SLAM3's success test
//   GrabImageMonocular JSVE_HOOK_BEGIN_FRAME() before Track(), JSVE_HOOK_LOG_FRAME() after it
//   Frame (monocular)  JSVE_HOOK_MASK_KEYPOINTS() after ExtractORB, before N = mvKeys.size() (src/Frame.cc
//                      includes this header without the implementation): with masks (begin_input), the
//                      keypoints on dynamic objects and their descriptors go before ORB-SLAM3
//                      undistorts, grids, matches or maps any of them
// and, where ORB-SLAM3 re-expresses a map without a new id (src/Map.cc and src/LocalMapping.cc include
// this header without the implementation):
//   Map::ApplyScaledRotation     JSVE_HOOK_WORLD_CHANGE(mnId, T, s) after the map is moved
//   LocalMapping::InitializeIMU  JSVE_HOOK_MAP_SNAPSHOT(map) at its start, JSVE_HOOK_MAP_CHANGED(map)
//   LocalMapping::ScaleRefinement  at its end (after the inertial BA that follows ApplyScaledRotation)
// and, for format v3's events (jsve::Event), JSVE_HOOK_EVENT(kEvent...) where ORB-SLAM3 resets a map
// (Tracking::ResetActiveMap, after it marks the lost frames; Tracking::Reset via JSVE_HOOK_RESET_ALL),
// starts one (Tracking::CreateMapInAtlas), merges maps (LoopClosing::MergeLocal, MergeLocal2), closes
// a loop (LoopClosing::CorrectLoop) and first sets a map's inertial flags (Map::SetImuInitialized,
// SetIniertialBA1, SetIniertialBA2). At the end of the run `write_trailer` (the driver calls it just
// before SaveTrajectoryEuRoC, once LocalMapping and LoopClosing are idle) writes the state
// SaveTrajectoryEuRoC reads: the trajectory lists, the keyframes they reference and the maps.
// Without a rule (set_rule) nothing in ORB-SLAM3's decisions changes: the hook only copies values.
// With one, JSVE_HOOK_DECIDE returns the rule's success test in place of ORB-SLAM3's (the same
// clauses, in the same order, with the rule's thresholds: jsve.core._machine.tracking_succeeds), and
// under imu-coast a failed frame gets back the pose TrackLocalMap started from (PredictStateIMU's,
// once the IMU is initialised). Logging after Track() returns catches every frame once, whichever
// early return Track() took.
//
// With a keypoint side file (open_keypoints), every logged frame's keypoints follow its log row
// (jsve_keypoints.hpp; docs/masks.md): where the masks apply (the input image's pixels), undistorted,
// and whether each counted in mnMatchesInliers (flagged where JSVE_HOOK_INLIERS runs, by the same
// condition).
//
// The driver (jsve_orbslam3.cc) opens and closes the log through open_log / close_log. One tracker
// per process: the hook's state is a process-wide singleton, used from the tracking thread only,
// except the world frames of the maps, which LocalMapping and LoopClosing change (under a mutex).
#pragma once

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <locale>
#include <map>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <vector>

#include "jsve_keypoints.hpp"
#include "jsve_log.hpp"
#include "jsve_orbslam3_lockstep.hpp"

namespace jsve_hook {

struct HookState {
    std::unique_ptr<jsve::LogWriter> log;
    int n_inliers = 0;  // Tracking::mnMatchesInliers of this frame (0 when TrackLocalMap did not run)
    int n_frustum = 0;  // nToMatch of this frame's SearchLocalPoints (0 when it did not run)
    double log_seconds = 0.0;  // time spent in log_frame, s (the hook's cost, reported by the driver)
    long imu_invalid_frames = 0;  // frames whose preintegration was NaN, logged as none (see log_frame)
    long pose_invalid_frames = 0;  // frames whose pose was NaN, logged without one (see log_frame)
    long keyframes = 0;  // keyframes in the active map after the last logged frame
    std::atomic<std::uint32_t> pending_events{0};  // jsve::Event bits since the last logged frame
    // A reset or a new map sets Tracking::mLastFrame to a default Frame, whose mTimeStamp Frame's default
    // constructor leaves uninitialised; the next frame constructed preintegrates from that stamp.
    std::atomic<bool> last_frame_cleared{false};  // set by those events, taken by the next frame
    bool previous_frame_cleared = false;  // this frame was constructed after such an event
    std::size_t entries_before = 0;  // length of Tracking::mlRelativeFramePoses before this frame's Track()
    std::vector<std::int64_t> entry_rows;  // the log row of each entry of Tracking::mlRelativeFramePoses
    std::string trailer_error;  // why the trailer was not written (empty: it was, or not yet asked)
    // The keypoint side file (open_keypoints): created at the first frame with keypoints, when
    // ORB-SLAM3 has computed the undistorted image bounds it records.
    std::unique_ptr<jsve::KeypointWriter> keypoints;
    std::string keypoints_path;
    jsve::Metadata keypoints_meta;
    std::vector<unsigned char> inlier_flags;  // per keypoint of this frame, set where TrackLocalMap counts
    int input_size[2] = {0, 0};  // [width, height] of the image given to TrackMonocular, px (begin_input)
    long keypoint_inlier_mismatches = 0;  // frames whose flags do not sum to n_inliers (see record_inliers)
};

// Dynamic-object masks in the loop: the driver sets each frame's instance map before TrackMonocular,
// and Frame's monocular constructor drops the keypoints Algorithm 1 puts on a car or a pedestrian
// (jsve::on_dynamic_object) before ORB-SLAM3 uses them (docs/masks.md, "Masks in the loop").
struct MaskState {
    bool on = false;            // every frame has a mask (the driver's --masks)
    jsve::InstanceMask mask;    // this frame's; empty outside TrackMonocular
    int n_before = 0;           // this frame's keypoints as extracted
    int n_removed = 0;          // ... and how many of them were dropped
    long total_removed = 0;
    std::vector<std::int64_t> t_ns;   // per logged frame, for the `masks` trailer
    std::vector<int> before, removed;
};

// The process's mask state (defined in Tracking.cc's translation unit).
MaskState& mask_state();

// Drops the keypoints on dynamic objects of `mask` and their descriptor rows, in place and in order,
// so that keys[i] still goes with descriptor row i (ORBextractor writes them paired). The keypoints
// are in an image of `width` x `height` px, the mask's image resized (jsve::source_coordinate). The
// kept rows are a view of the first rows of the same matrix: nothing is allocated. Returns how many it
// dropped. KeyPoints: a std::vector of cv::KeyPoint; Descriptors: cv::Mat (ptr, cols, elemSize, rowRange).
template <class KeyPoints, class Descriptors>
std::size_t drop_dynamic_keypoints(const jsve::InstanceMask& mask, KeyPoints& keys, Descriptors& descriptors,
                                   int width, int height) {
    const std::size_t row_bytes = static_cast<std::size_t>(descriptors.cols) * descriptors.elemSize();
    std::size_t kept = 0;
    for (std::size_t i = 0; i < keys.size(); ++i) {
        const float x = jsve::source_coordinate(keys[i].pt.x, mask.width, width);
        const float y = jsve::source_coordinate(keys[i].pt.y, mask.height, height);
        if (jsve::on_dynamic_object(mask, static_cast<double>(x), static_cast<double>(y))) continue;
        if (kept != i) {
            keys[kept] = keys[i];
            std::memcpy(descriptors.ptr(static_cast<int>(kept)), descriptors.ptr(static_cast<int>(i)), row_bytes);
        }
        ++kept;
    }
    const std::size_t dropped = keys.size() - kept;
    if (dropped > 0) {
        keys.erase(keys.begin() + static_cast<std::ptrdiff_t>(kept), keys.end());
        descriptors = descriptors.rowRange(0, static_cast<int>(kept));
    }
    return dropped;
}

// JSVE_HOOK_MASK_KEYPOINTS: this frame's mask applied to Frame::mvKeys and mDescriptors, extracted
// from an image of `width` x `height` px (nothing without masks); the counts kept for the log's
// `masks` trailer.
template <class KeyPoints, class Descriptors>
void mask_keypoints(KeyPoints& keys, Descriptors& descriptors, int width, int height) {
    MaskState& m = mask_state();
    if (!m.on) return;
    m.n_before = static_cast<int>(keys.size());
    m.n_removed = static_cast<int>(drop_dynamic_keypoints(m.mask, keys, descriptors, width, height));
    m.total_removed += m.n_removed;
}

// Turns masks on (before the first frame): every frame must then get one through begin_input.
void enable_masks();

// The image the driver is about to pass to TrackMonocular: its size (px, before ORB-SLAM3 resizes it
// to its settings' Camera.newWidth x newHeight) and its mask (held by the caller until end_input; an
// empty view without masks).
void begin_input(int width, int height, const jsve::InstanceMask& mask);
void end_input();

// The `masks` trailer: the mask source and, per logged frame, t_ns, the keypoints as extracted and
// how many were dropped (n_extracted is what is left). Call before close_log.
bool write_masks_trailer(const std::string& source, std::string* error);

// The process's hook state (defined in Tracking.cc's translation unit).
HookState& state();

// An event of ORB-SLAM3 (any thread): set on the next logged frame's `events`.
inline void event(std::uint32_t bit) {
    constexpr std::uint32_t clears_last_frame = jsve::kEventReset | jsve::kEventResetAll | jsve::kEventNewMap;
    state().pending_events.fetch_or(bit);
    if (bit & clears_last_frame) state().last_frame_cleared = true;
}

// Opens `path` (format v3, via jsve::LogWriter; refuses an existing file unless `overwrite`).
// Returns false with `*error` set on failure.
bool open_log(const std::string& path, const jsve::Metadata& meta, bool overwrite, std::string* error);

// Closes the log: writes the end marker and renames `<path>.partial` to `<path>`; first the keypoint
// side file, if any (a side file that cannot be finished leaves both `.partial`).
bool close_log(std::string* error);

// Writes every logged frame's keypoints to `path` (jsve_keypoints.hpp) with `meta` (the log's run id)
// plus image_size and ORB-SLAM3's image_bounds. An existing `path` is refused unless `overwrite`,
// which removes it now. Call after open_log, before the first frame.
bool open_keypoints(const std::string& path, const jsve::Metadata& meta, bool overwrite, std::string* error);

// In a child of fork_parked: the log goes on at `path` (a copy of every row so far; LogWriter::continue_as).
bool continue_log_as(const std::string& path, std::string* error);

// Format v3's `orbslam3` trailer: what System::SaveTrajectoryEuRoC reads at the end of the run (the
// trajectory lists, the keyframes they and the logged frames reference, the maps). Call after
// System::Shutdown and before close_log; it first waits (up to `timeout_s`) for LocalMapping and
// LoopClosing to finish. False, with `*error` set and no trailer written, when they do not.
bool write_trailer(double timeout_s, std::string* error);

// A jsve rule (jsve.core._rules): ORB-SLAM3's success test with a score and thresholds of its own.
// A frame fails inside the relocalisation window below `reloc`; in RECENTLY_LOST it succeeds above
// `recovery`; else it fails below `imu_init` (IMU initialised, or a stereo sensor) or `not_init`.
// The score is the inlier count (ORB-SLAM3's own thresholds for IMU_MONOCULAR: 15 / 50 / 50 / 10), or
// an SVE combination of S_a, S_b, S_c (jsve.core._sve.Combination: the family and its three inputs).
enum class ScoreKind { kInliers, kSve };
enum class SveInputs { kJsve, kAuthorsEq1, kAuthorsOption1 };  // Combination.inputs

struct Rule {
    ScoreKind kind = ScoreKind::kInliers;
    SveInputs inputs = SveInputs::kJsve;
    double w_a = 0.5, u_b = 0.5, p = 1.0, q = 1.0, rho = 0.25;  // the SVE combination
    double n_features = 1000.0;                                  // ORBextractor.nFeatures (S_a of Eq.1)
    double imu_init = 15.0, not_init = 50.0, reloc = 50.0, recovery = 10.0;
};

// The counts one frame's score is made of (the log's n_extracted, n_inliers, n_frustum, bin_*).
struct FrameCounts {
    int n_extracted = 0, n_inliers = 0, n_frustum = 0;
    int bins[64] = {};
};

// M_p([x1, x2]; [w, 1 - w]) of non-negative x: jsve.core._sve.power_mean's definition (p -> 0: the
// geometric mean with its first-order term; a zero entry of positive weight gives 0 for p <= 0).
inline double power_mean2(double x1, double x2, double w, double p) {
    const bool pos1 = x1 > 0.0, pos2 = x2 > 0.0;
    const double w2 = 1.0 - w;
    const bool near_zero_p = std::fabs(p) < 1e-6;
    if (((!pos1 && w > 0.0) || (!pos2 && w2 > 0.0)) && (near_zero_p || p <= 0.0)) return 0.0;
    const double l1 = pos1 ? std::log(x1) : 0.0, l2 = pos2 ? std::log(x2) : 0.0;
    if (near_zero_p) {
        const double mean = w * l1 + w2 * l2;
        const double var = w * (l1 - mean) * (l1 - mean) + w2 * (l2 - mean) * (l2 - mean);
        return std::exp(mean + 0.5 * p * var);
    }
    const double excess = w * (pos1 ? std::expm1(p * l1) : -1.0) + w2 * (pos2 ? std::expm1(p * l2) : -1.0);
    return excess > -1.0 ? std::exp(std::log1p(excess) / p) : 0.0;
}

inline double clamp01(double x) { return x < 0.0 ? 0.0 : (x > 1.0 ? 1.0 : x); }

// S_b = 1 - chi2 / chi2_w over the 64 bins with E = N / 64 (jsve.core._sve.s_b); 0 when N = 0.
inline double sve_s_b(const FrameCounts& c, bool clamp) {
    if (c.n_extracted <= 0) return 0.0;
    const double n = c.n_extracted, expected = n / 64.0;
    double sum_sq = 0.0;
    for (int k = 0; k < 64; ++k) sum_sq += (c.bins[k] - expected) * (c.bins[k] - expected);
    const double value = 1.0 - 64.0 * sum_sq / (7.0 * n * n);
    return clamp ? clamp01(value) : value;
}

// S_c = N_inliers / N_frustum, 0 when N_frustum = 0 (jsve.core._sve.s_c).
inline double sve_s_c(const FrameCounts& c, bool clamp) {
    const double value = c.n_frustum > 0 ? double(c.n_inliers) / c.n_frustum : 0.0;
    return clamp ? clamp01(value) : value;
}

// The rule's score of one frame (jsve.core._rules: InlierRule.score, SVERule.score).
inline double rule_score(const Rule& r, const FrameCounts& c) {
    if (r.kind == ScoreKind::kInliers) return c.n_inliers;
    const double ratio = c.n_extracted > 0 ? double(c.n_inliers) / c.n_extracted : 0.0;
    if (r.inputs == SveInputs::kJsve) {
        const double s_a = r.rho > 0.0 ? std::min(ratio / r.rho, 1.0) : 0.0;
        return power_mean2(s_a, power_mean2(sve_s_b(c, true), sve_s_c(c, true), r.u_b, r.q), r.w_a, r.p);
    }
    // The authors' builds: linear, unclamped S_b and S_c (p = q = 1, checked where the rule is read).
    const double a = r.inputs == SveInputs::kAuthorsEq1 ? c.n_extracted / r.n_features
                                                        : (r.rho > 0.0 ? clamp01(ratio / r.rho) : 0.0);
    return r.w_a * a + (1.0 - r.w_a) * (r.u_b * sve_s_b(c, false) + (1.0 - r.u_b) * sve_s_c(c, false));
}

// ORB-SLAM3's success test with the rule's score and thresholds (jsve.core._machine.tracking_succeeds).
inline bool rule_succeeds(const Rule& r, double score, bool in_reloc, bool recently_lost, bool imu_ok, bool stereo) {
    const bool fail_reloc = in_reloc && score < r.reloc;
    const bool recover = recently_lost && score > r.recovery;
    const bool pass_main = !(score < ((imu_ok || stereo) ? r.imu_init : r.not_init));
    return !fail_reloc && (recover || pass_main);
}

// The driver's rule options into `rule` (its nFeatures kept): `--rule-inliers IMU_INIT,NOT_INIT,RELOC,
// RECOVERY` or `--rule-sve INPUTS,W_A,U_B,P,Q,RHO,IMU_INIT,NOT_INIT,RELOC,RECOVERY` (INPUTS: jsve,
// authors-eq1, authors-option1; the authors' inputs need P = Q = 1). False with `*error` set otherwise.
inline bool parse_rule(const std::string& flag, const std::string& text, Rule* rule, std::string* error) {
    const bool sve = flag == "--rule-sve";
    std::vector<std::string> items;
    std::size_t start = 0;
    for (std::size_t comma = text.find(','); ; comma = text.find(',', start)) {
        items.push_back(text.substr(start, comma == std::string::npos ? std::string::npos : comma - start));
        if (comma == std::string::npos) break;
        start = comma + 1;
    }
    const std::size_t expected = sve ? 10 : 4;
    if (items.size() != expected) {
        *error = sve ? "--rule-sve wants INPUTS,W_A,U_B,P,Q,RHO,IMU_INIT,NOT_INIT,RELOC,RECOVERY"
                     : "--rule-inliers wants IMU_INIT,NOT_INIT,RELOC,RECOVERY";
        return false;
    }
    std::vector<double> t;
    for (std::size_t k = sve ? 1 : 0; k < items.size(); ++k) {
        std::istringstream in(items[k]);
        in.imbue(std::locale::classic());  // '.' whatever LC_NUMERIC says
        double d = 0.0;
        in >> d;
        if (items[k].empty() || !in || in.peek() != EOF || !std::isfinite(d)) {
            *error = flag + ": '" + items[k] + "' is not a number";
            return false;
        }
        t.push_back(d);
    }
    Rule r;
    r.n_features = rule->n_features;
    if (sve) {
        const std::string& inputs = items[0];
        if (inputs == "jsve") r.inputs = SveInputs::kJsve;
        else if (inputs == "authors-eq1") r.inputs = SveInputs::kAuthorsEq1;
        else if (inputs == "authors-option1") r.inputs = SveInputs::kAuthorsOption1;
        else {
            *error = "--rule-sve: INPUTS must be jsve, authors-eq1 or authors-option1, got '" + inputs + "'";
            return false;
        }
        if (r.inputs != SveInputs::kJsve && (t[2] != 1.0 || t[3] != 1.0)) {
            *error = "--rule-sve: the authors' inputs are combined linearly: P and Q must be 1";
            return false;
        }
        r.kind = ScoreKind::kSve;
        r.w_a = t[0], r.u_b = t[1], r.p = t[2], r.q = t[3], r.rho = t[4];
        t.erase(t.begin(), t.begin() + 5);
    }
    r.imu_init = t[0], r.not_init = t[1], r.reloc = t[2], r.recovery = t[3];
    *rule = r;
    return true;
}

// Replace ORB-SLAM3's success test by `rule` from the next frame on; `coast`: a failed frame keeps
// the pose TrackLocalMap started from instead of the optimised one (switch model "imu-coast").
void set_rule(const Rule& rule, bool coast);
bool rule_active();

// A similarity x' = s R(q) x + t between world frames (q wxyz); the identity by default.
struct Similarity {
    double q[4] = {1.0, 0.0, 0.0, 0.0};
    double t[3] = {0.0, 0.0, 0.0};
    double s = 1.0;
};

// Map `map_id` was re-expressed by `change` (Map::ApplyScaledRotation's T and s): its world frame is
// now change o (what it was). Thread-safe (called from LocalMapping and LoopClosing).
void world_change(std::int64_t map_id, const Similarity& change);

// The similarity from map `map_id`'s first world frame to its current one (the log's world_* columns).
Similarity world_frame(std::int64_t map_id);

// Keyframe camera centres of a map: {keyframe id, x, y, z (m)} per keyframe that is not bad.
using Centres = std::vector<std::array<double, 4>>;

// Remember the map's keyframe centres (before LocalMapping changes the map, or right after
// ApplyScaledRotation moved it).
void map_snapshot(std::int64_t map_id, Centres centres);

// LocalMapping finished changing the map (the inertial BA after an IMU initialisation or a scale
// refinement moves every keyframe, mostly by a scale): the similarity that best maps the snapshot's
// centres onto these (Umeyama, over the keyframes in both) is one more change of the world frame.
void map_changed(std::int64_t map_id, const Centres& centres);

// The exact int64 stamp from an image named `<t_ns>.png` (EuRoC's stamps have 19 digits), else the
// double stamp rounded (a double at 1.4e9 s is spaced 2.4e-7 s: the name is the exact source when
// there is one).
inline std::int64_t stamp_ns(const std::string& name, double t_s) {
    const std::size_t slash = name.find_last_of('/');
    std::string stem = name.substr(slash == std::string::npos ? 0 : slash + 1);
    stem = stem.substr(0, stem.find('.'));
    bool digits = !stem.empty() && stem.size() <= 19;
    for (char c : stem) digits = digits && c >= '0' && c <= '9';
    // 19 digits fit int64 up to its largest value; digit strings of one length compare as numbers
    const bool fits = digits && (stem.size() < 19 || stem <= "9223372036854775807");
    return fits ? std::stoll(stem) : std::llround(t_s * 1e9);
}

}  // namespace jsve_hook

#define JSVE_HOOK_FRUSTUM(count) (::jsve_hook::state().n_frustum = static_cast<int>(count))
// Expands inside Tracking::TrackLocalMap, right after it counts mnMatchesInliers.
#define JSVE_HOOK_INLIERS(count) ::jsve_hook::record_inliers(static_cast<int>(count), mCurrentFrame, mbOnlyTracking)
#define JSVE_HOOK_BEGIN_FRAME()                                                                    \
    (::jsve_hook::state().n_inliers = ::jsve_hook::state().n_frustum = 0,                          \
     ::jsve_hook::state().inlier_flags.clear(),                                                    \
     ::jsve_hook::state().entries_before = mlRelativeFramePoses.size(),                              \
     ::jsve_hook::state().previous_frame_cleared = ::jsve_hook::state().last_frame_cleared.exchange(false))
// Expands inside Frame's monocular constructor, after ExtractORB.
#define JSVE_HOOK_MASK_KEYPOINTS() ::jsve_hook::mask_keypoints(mvKeys, mDescriptors, imGray.cols, imGray.rows)
#define JSVE_HOOK_EVENT(bit) ::jsve_hook::event(::jsve::bit)
// Tracking::Reset clears the trajectory lists (and every map).
#define JSVE_HOOK_RESET_ALL() (::jsve_hook::event(::jsve::kEventResetAll), ::jsve_hook::state().entry_rows.clear())
#define JSVE_HOOK_SAVE_PREDICTION() ::jsve_hook::save_prediction(mCurrentFrame)
#define JSVE_HOOK_DECIDE()                                                                         \
    do {                                                                                           \
        if (::jsve_hook::rule_active())                                                            \
            return ::jsve_hook::decide(mCurrentFrame, mnMatchesInliers,                            \
                                       mCurrentFrame.mnId < mnLastRelocFrameId + mMaxFrames,      \
                                       mState == RECENTLY_LOST, mpAtlas->isImuInitialized(),       \
                                       mSensor == System::IMU_STEREO || mSensor == System::IMU_RGBD); \
    } while (0)
// The centres of a range of ORB_SLAM3::KeyFrame* (a std::set or std::vector of them).
#define JSVE_HOOK_CENTRES(keyframes)                                                               \
    [&]() {                                                                                        \
        ::jsve_hook::Centres centres_;                                                             \
        for (ORB_SLAM3::KeyFrame* kf_ : (keyframes)) {                                             \
            if (kf_ == nullptr || kf_->isBad()) continue;                                          \
            const Eigen::Vector3f c_ = kf_->GetCameraCenter();                                     \
            centres_.push_back({double(kf_->mnId), double(c_(0)), double(c_(1)), double(c_(2))});   \
        }                                                                                          \
        return centres_;                                                                           \
    }()
// Expands inside Map::ApplyScaledRotation (T: Sophus::SE3f, s: float), which holds the map's mutex:
// the keyframes are read from its own set.
#define JSVE_HOOK_WORLD_CHANGE(map_id, T, s)                                                      \
    do {                                                                                           \
        ::jsve_hook::Similarity change_;                                                           \
        const Eigen::Quaterniond q_ = (T).unit_quaternion().cast<double>();                        \
        change_.q[0] = q_.w(); change_.q[1] = q_.x(); change_.q[2] = q_.y(); change_.q[3] = q_.z(); \
        for (int i_ = 0; i_ < 3; ++i_) change_.t[i_] = static_cast<double>((T).translation()(i_)); \
        change_.s = static_cast<double>(s);                                                        \
        ::jsve_hook::world_change(static_cast<std::int64_t>(map_id), change_);                     \
        ::jsve_hook::map_snapshot(static_cast<std::int64_t>(map_id), JSVE_HOOK_CENTRES(mspKeyFrames)); \
    } while (0)
#define JSVE_HOOK_MAP_SNAPSHOT(map) \
    ::jsve_hook::map_snapshot(static_cast<std::int64_t>((map)->GetId()), JSVE_HOOK_CENTRES((map)->GetAllKeyFrames()))
#define JSVE_HOOK_MAP_CHANGED(map) \
    ::jsve_hook::map_changed(static_cast<std::int64_t>((map)->GetId()), JSVE_HOOK_CENTRES((map)->GetAllKeyFrames()))
// Expands inside a Tracking member function: reads its protected members.
#define JSVE_HOOK_LOG_FRAME()                                                                      \
    ::jsve_hook::log_frame(mCurrentFrame, static_cast<int>(mState), mpAtlas,                       \
                           ::jsve_hook::TrackerView{&mlRelativeFramePoses, &mlpReferences, &mlbLost,  \
                                                    mpAtlas, mpLocalMapper, mpLoopClosing},           \
                           mImGray.cols, mImGray.rows)

#ifdef JSVE_HOOK_IMPLEMENTATION

#include <chrono>
#include <list>
#include <set>
#include <thread>

namespace jsve_hook {

// What the trailer reads of the tracker (Tracking's protected members, gathered where they are
// visible: JSVE_HOOK_LOG_FRAME expands inside Tracking::GrabImageMonocular).
struct TrackerView {
    const std::list<Sophus::SE3f>* relative = nullptr;   // mlRelativeFramePoses (T_cr)
    const std::list<ORB_SLAM3::KeyFrame*>* references = nullptr;  // mlpReferences
    const std::list<bool>* lost = nullptr;               // mlbLost
    ORB_SLAM3::Atlas* atlas = nullptr;
    ORB_SLAM3::LocalMapping* local_mapping = nullptr;
    ORB_SLAM3::LoopClosing* loop_closing = nullptr;
};

TrackerView& tracker_view() {
    static TrackerView v;
    return v;
}

// Every keyframe a logged frame named as its reference (ORB-SLAM3 never deletes a keyframe object: a
// culled one is flagged bad, a reset map's are detached from it), for the trailer's keyframe table.
std::set<ORB_SLAM3::KeyFrame*>& logged_references() {
    static std::set<ORB_SLAM3::KeyFrame*> seen;
    return seen;
}

HookState& state() {
    static HookState s;
    return s;
}

MaskState& mask_state() {
    static MaskState m;
    return m;
}

void enable_masks() { mask_state().on = true; }

void begin_input(int width, int height, const jsve::InstanceMask& mask) {
    state().input_size[0] = width, state().input_size[1] = height;
    mask_state().mask = mask;
}

void end_input() { mask_state().mask = jsve::InstanceMask(); }

// JSON list of numbers.
template <class Values>
void append_numbers(std::string& out, const Values& values) {
    out += '[';
    for (std::size_t i = 0; i < values.size(); ++i) {
        if (i) out += ',';
        out += std::to_string(values[i]);
    }
    out += ']';
}

bool write_masks_trailer(const std::string& source, std::string* error) {
    HookState& s = state();
    const MaskState& m = mask_state();
    if (!s.log) {
        if (error) *error = "no log is open";
        return false;
    }
    std::string out = "{\"source\":";
    jsve::detail::append_json_string(out, source);
    out += ",\"classes\":[" + std::to_string(jsve::kClassCar) + "," + std::to_string(jsve::kClassPedestrian) + "]";
    out += ",\"t_ns\":";
    append_numbers(out, m.t_ns);
    out += ",\"n_before\":";
    append_numbers(out, m.before);
    out += ",\"n_removed\":";
    append_numbers(out, m.removed);
    out += '}';
    if (s.log->trailer("masks", out) != jsve::Status::kOk) {
        if (error) *error = s.log->last_error();
        return false;
    }
    return true;
}

// TrackLocalMap's inlier count, and with a keypoint file the flag of each keypoint by the count's own
// condition (a map point, not an outlier, and observed by a keyframe outside localisation-only mode),
// read right after the count. In a paced run LocalMapping may change a point's observations in
// between; the frames where the flags then miss the count are counted (keypoint_inlier_mismatches).
inline void record_inliers(int count, const ORB_SLAM3::Frame& frame, bool only_tracking) {
    HookState& s = state();
    s.n_inliers = count;
    if (!s.keypoints) return;
    s.inlier_flags.assign(static_cast<std::size_t>(frame.N), 0);
    for (int i = 0; i < frame.N; ++i) {
        ORB_SLAM3::MapPoint* point = frame.mvpMapPoints[i];
        s.inlier_flags[i] = point && !frame.mvbOutlier[i] && (only_tracking || point->Observations() > 0);
    }
}

bool open_keypoints(const std::string& path, const jsve::Metadata& meta, bool overwrite, std::string* error) {
    HookState& s = state();
    // The file itself is created at the first frame with keypoints; an older one must not wait beside it.
    if (std::FILE* existing = std::fopen(path.c_str(), "rb")) {
        std::fclose(existing);
        if (!overwrite || std::remove(path.c_str()) != 0) {
            if (error) *error = path + (overwrite ? ": cannot remove it" : ": exists");
            return false;
        }
    }
    s.keypoints = std::make_unique<jsve::KeypointWriter>();
    s.keypoints_path = path;
    s.keypoints_meta = meta;
    return true;
}

// Creates the keypoint file: the run's metadata, the input image's size (x, y are in its pixels) and,
// once ORB-SLAM3 has computed them (on its first frame with keypoints), the undistorted image bounds its
// grid spans (ux, uy are in those of the image it tracks, resized when its settings say so).
inline void start_keypoints(bool with_bounds) {
    HookState& s = state();
    jsve::Metadata meta = s.keypoints_meta;
    meta.set("image_size", {s.input_size[0], s.input_size[1]});
    if (with_bounds)
        meta.set("image_bounds", {static_cast<double>(ORB_SLAM3::Frame::mnMinX), static_cast<double>(ORB_SLAM3::Frame::mnMaxX),
                                  static_cast<double>(ORB_SLAM3::Frame::mnMinY), static_cast<double>(ORB_SLAM3::Frame::mnMaxY)});
    jsve::KeypointOptions options;
    options.overwrite = true;  // open_keypoints refused or removed an older file
    options.on_error = jsve::OnError::kReturn;
    if (s.keypoints->open(s.keypoints_path, meta, options) != jsve::Status::kOk)
        throw jsve::LogError(jsve::Status::kIoError, s.keypoints->last_error());
}

// The frame's keypoints after its log row (docs/masks.md, "What a C++ writer would emit"); ORB-SLAM3
// extracted them from an image of `width` x `height` px.
inline void log_keypoints(const ORB_SLAM3::Frame& frame, std::int64_t t_ns, int n_inliers, int width, int height) {
    HookState& s = state();
    if (!s.keypoints) return;
    if (!s.keypoints->is_open()) {
        if (frame.N == 0) return;
        start_keypoints(true);
    }
    const std::size_t n = static_cast<std::size_t>(frame.N);
    const bool flagged = s.inlier_flags.size() == n;  // TrackLocalMap ran on this frame
    int sum = 0;
    for (std::size_t i = 0; i < n; ++i) {
        const cv::KeyPoint& k = frame.mvKeys[i];
        const cv::KeyPoint& u = frame.mvKeysUn[i];
        const bool inlier = flagged && s.inlier_flags[i];
        sum += inlier;
        const float x = jsve::source_coordinate(k.pt.x, s.input_size[0], width);
        const float y = jsve::source_coordinate(k.pt.y, s.input_size[1], height);
        if (s.keypoints->write(t_ns, x, y, u.pt.x, u.pt.y, k.octave, inlier) != jsve::Status::kOk)
            throw jsve::LogError(jsve::Status::kFailed, s.keypoints->last_error());
    }
    if (sum != n_inliers) ++s.keypoint_inlier_mismatches;
    if (s.keypoints->flush() != jsve::Status::kOk) throw jsve::LogError(jsve::Status::kIoError, s.keypoints->last_error());
}

bool settle_frame() {
    ORB_SLAM3::LoopClosing* loop_closing = tracker_view().loop_closing;
    return loop_closing == nullptr || settle(loop_closing);
}

int fork_parked() {
    const TrackerView& v = tracker_view();
    HookState& s = state();
    if (s.log && s.log->flush() != jsve::Status::kOk) return -1;
    std::fflush(nullptr);  // a child must not write this process's buffered console output again
    return fork_parked(v.local_mapping, v.loop_closing);
}

bool continue_log_as(const std::string& path, std::string* error) {
    HookState& s = state();
    if (!s.log || s.log->continue_as(path) != jsve::Status::kOk) {
        if (error) *error = s.log ? s.log->last_error() : "no log is open";
        return false;
    }
    return true;
}

bool open_log(const std::string& path, const jsve::Metadata& meta, bool overwrite, std::string* error) {
    jsve::Options options;
    options.overwrite = overwrite;
    // Flush every frame: ORB-SLAM3 can abort (Sophus' NaN check after a map reset), and an abort does
    // not flush stdio; the `.partial` log then still holds every frame up to the one that crashed.
    options.flush_every = 1;
    options.on_error = jsve::OnError::kReturn;
    options.world_frame = true;  // the world_* columns: the maps' re-expressions (jsve.io._world)
    options.keyframes = true;    // format v3: events, the saved trajectory's entries (write_trailer)
    auto writer = std::make_unique<jsve::LogWriter>();
    if (writer->open(path, meta, options) != jsve::Status::kOk) {
        if (error) *error = writer->last_error();
        return false;
    }
    state().log = std::move(writer);
    return true;
}

bool close_log(std::string* error) {
    HookState& s = state();
    if (!s.log) return true;
    if (s.keypoints) {
        bool ok = true;
        try {
            if (!s.keypoints->is_open()) start_keypoints(false);  // no frame had keypoints: no bounds either
        } catch (const jsve::LogError&) {
            ok = false;
        }
        ok = ok && s.keypoints->close() == jsve::Status::kOk;
        if (!ok) {
            if (error) *error = s.keypoints->last_error();
            s.log->abandon();
            s.log.reset();
            return false;
        }
    }
    const bool ok = s.log->close() == jsve::Status::kOk;
    if (!ok && error) *error = s.log->last_error();
    s.log.reset();
    return ok;
}

struct RuleState {
    bool active = false, coast = false;
    Rule rule;
    bool saved = false, has_velocity = false;  // the pose TrackLocalMap started from, for imu-coast
    Sophus::SE3f pose;
    Eigen::Vector3f velocity;
};

RuleState& rule_state() {
    static RuleState r;
    return r;
}

void set_rule(const Rule& rule, bool coast) {
    RuleState& r = rule_state();
    r.active = true;
    r.rule = rule;
    r.coast = coast;
}

bool rule_active() { return rule_state().active; }

struct WorldFrames {
    std::mutex mutex;
    std::map<std::int64_t, Similarity> of_map;  // maps never re-expressed are absent (the identity)
    std::map<std::int64_t, Centres> snapshot;   // keyframe centres before the change in progress
};

WorldFrames& world_frames() {
    static WorldFrames w;
    return w;
}

void world_change(std::int64_t map_id, const Similarity& change) {
    // Composition change o old: s = s_c s_o, R = R_c R_o, t = s_c R_c t_o + t_c.
    const Eigen::Quaterniond qc(change.q[0], change.q[1], change.q[2], change.q[3]);
    const Eigen::Vector3d tc(change.t[0], change.t[1], change.t[2]);
    WorldFrames& w = world_frames();
    std::lock_guard<std::mutex> lock(w.mutex);
    Similarity& old = w.of_map[map_id];
    const Eigen::Quaterniond qo(old.q[0], old.q[1], old.q[2], old.q[3]);
    const Eigen::Quaterniond q = (qc * qo).normalized();
    const Eigen::Vector3d t = change.s * (qc * Eigen::Vector3d(old.t[0], old.t[1], old.t[2])) + tc;
    old.q[0] = q.w(); old.q[1] = q.x(); old.q[2] = q.y(); old.q[3] = q.z();
    for (int i = 0; i < 3; ++i) old.t[i] = t(i);
    old.s *= change.s;
}

void map_snapshot(std::int64_t map_id, Centres centres) {
    WorldFrames& w = world_frames();
    std::lock_guard<std::mutex> lock(w.mutex);
    w.snapshot[map_id] = std::move(centres);
}

void map_changed(std::int64_t map_id, const Centres& centres) {
    Centres before;
    {
        WorldFrames& w = world_frames();
        std::lock_guard<std::mutex> lock(w.mutex);
        const auto it = w.snapshot.find(map_id);
        if (it == w.snapshot.end()) return;
        before = std::move(it->second);
        w.snapshot.erase(it);
    }
    std::map<double, Eigen::Vector3d> old;
    for (const auto& c : before) old[c[0]] = Eigen::Vector3d(c[1], c[2], c[3]);
    std::vector<Eigen::Vector3d> src, dst;
    for (const auto& c : centres) {
        const auto it = old.find(c[0]);
        if (it == old.end()) continue;
        src.push_back(it->second);
        dst.push_back(Eigen::Vector3d(c[1], c[2], c[3]));
    }
    if (src.size() < 3) return;  // too few keyframes in both to fix a similarity
    Eigen::Matrix3Xd a(3, src.size()), b(3, dst.size());
    for (std::size_t i = 0; i < src.size(); ++i) a.col(Eigen::Index(i)) = src[i], b.col(Eigen::Index(i)) = dst[i];
    const Eigen::Matrix4d m = Eigen::umeyama(a, b, true);  // b = s R a + t
    const double scale = std::cbrt(m.topLeftCorner<3, 3>().determinant());
    if (!m.allFinite() || !(scale > 0.0)) return;
    const Eigen::Quaterniond q(Eigen::Matrix3d(m.topLeftCorner<3, 3>() / scale));
    Similarity change;
    change.q[0] = q.w(), change.q[1] = q.x(), change.q[2] = q.y(), change.q[3] = q.z();
    for (int i = 0; i < 3; ++i) change.t[i] = m(i, 3);
    change.s = scale;
    world_change(map_id, change);
}

Similarity world_frame(std::int64_t map_id) {
    WorldFrames& w = world_frames();
    std::lock_guard<std::mutex> lock(w.mutex);
    const auto it = w.of_map.find(map_id);
    return it == w.of_map.end() ? Similarity() : it->second;
}

inline void save_prediction(ORB_SLAM3::Frame& frame) {
    RuleState& r = rule_state();
    r.saved = r.coast && frame.HasPose();
    if (!r.saved) return;
    r.pose = frame.GetPose();
    r.has_velocity = frame.HasVelocity();
    if (r.has_velocity) r.velocity = frame.GetVelocity();
}

inline bool decide(ORB_SLAM3::Frame& frame, int inliers, bool in_reloc, bool recently_lost, bool imu_ok,
                   bool stereo) {
    RuleState& r = rule_state();
    FrameCounts counts;
    counts.n_extracted = frame.N;
    counts.n_inliers = inliers;
    counts.n_frustum = state().n_frustum;
    if (r.rule.kind == ScoreKind::kSve) {  // the bins as the log has them (jsve::fill_bins_from_grid)
        jsve::Frame binned;
        jsve::fill_bins_from_grid(binned, [&](int c, int row) { return frame.mGrid[c][row].size(); });
        std::copy(binned.bins, binned.bins + 64, counts.bins);
    }
    const bool ok = rule_succeeds(r.rule, rule_score(r.rule, counts), in_reloc, recently_lost, imu_ok, stereo);
    if (!ok && r.saved) {
        frame.SetPose(r.pose);
        if (r.has_velocity) frame.SetVelocity(r.velocity);
    }
    return ok;
}

template <class Vec>
void copy3(double out[3], const Vec& v) {
    for (int i = 0; i < 3; ++i) out[i] = static_cast<double>(v(i));
}

// wxyz of a rotation matrix, normalised in double precision.
template <class Mat>
void copy_quaternion(double out[4], const Mat& r) {
    const Eigen::Quaterniond q = Eigen::Quaterniond(r.template cast<double>()).normalized();
    out[0] = q.w(); out[1] = q.x(); out[2] = q.y(); out[3] = q.z();
}

// One log row for the frame Track() just processed (docs/frontend.md section 3 maps each field).
// A frame the writer refuses fails the writer (jsve::LogError is thrown: the run stops, the log
// stays `.partial`): a silently dropped frame would bias every replay where tracking struggles.
// [qw, qx, qy, qz, tx, ty, tz] of a Sophus SE3f, exactly (float to double).
inline void copy_pose(double q[4], double t[3], const Sophus::SE3f& pose) {
    const Eigen::Quaternionf& r = pose.unit_quaternion();
    q[0] = r.w(), q[1] = r.x(), q[2] = r.y(), q[3] = r.z();
    for (int i = 0; i < 3; ++i) t[i] = static_cast<double>(pose.translation()(i));
}

inline void log_frame(ORB_SLAM3::Frame& frame, int tracking_state, ORB_SLAM3::Atlas* atlas, const TrackerView& view,
                      int image_width, int image_height) {
    HookState& s = state();
    if (!s.log) return;
    tracker_view() = view;
    const auto start = std::chrono::steady_clock::now();
    jsve::Frame f;
    // Format v3: the events since the last frame, and the frame's place in ORB-SLAM3's saved trajectory.
    f.events = s.pending_events.exchange(0);
    const std::size_t entries = view.relative->size();
    f.traj = entries == s.entries_before + 1;
    if (f.traj && view.references->back() != nullptr) {
        // The entry SaveTrajectoryEuRoC will read (Track() appends it, or repeats the last one when the
        // frame has no pose, Tracking.cc l.2300-2318).
        f.ref_kf = static_cast<std::int64_t>(view.references->back()->mnId);
        copy_pose(f.rel_q, f.rel_p, view.relative->back());
        logged_references().insert(view.references->back());
        s.entry_rows.push_back(s.log->frames());
    } else {
        f.traj = false;
        if (entries == s.entries_before + 1) s.entry_rows.push_back(-1);  // an entry without a keyframe
        if (frame.isSet() && frame.mpReferenceKF != nullptr) {
            f.ref_kf = static_cast<std::int64_t>(frame.mpReferenceKF->mnId);
            copy_pose(f.rel_q, f.rel_p, frame.GetPose() * frame.mpReferenceKF->GetPoseInverse());
            logged_references().insert(frame.mpReferenceKF);
        }
    }
    bool rel_finite = true;
    for (int i = 0; i < 3; ++i) rel_finite = rel_finite && std::isfinite(f.rel_p[i]);
    for (int i = 0; i < 4; ++i) rel_finite = rel_finite && std::isfinite(f.rel_q[i]);
    if (!rel_finite) f.ref_kf = -1, f.traj = false;
    if (f.ref_kf >= 0) {  // a float quaternion's norm can be off 1 by more than the format allows
        const double n = std::sqrt(f.rel_q[0] * f.rel_q[0] + f.rel_q[1] * f.rel_q[1] + f.rel_q[2] * f.rel_q[2] +
                                   f.rel_q[3] * f.rel_q[3]);
        for (int i = 0; i < 4; ++i) f.rel_q[i] /= n;
    }
    f.t_ns = stamp_ns(frame.mNameFile, frame.mTimeStamp);
    f.state = tracking_state;
    // Track() can return before tracking the frame while mState still says OK: when LocalMapping
    // flagged a bad IMU initialisation (Tracking.cc l.1805-1810: ResetActiveMap is requested and runs
    // at the next frame) or after a timestamp jump. The frame has no pose and the map is gone: it is
    // logged as LOST, which is what the state machine makes of it (a failure before BA2 resets).
    if (!frame.isSet() && (f.state == 2 || f.state == 3 || f.state == 5)) f.state = 4;
    ORB_SLAM3::Map* map = atlas->GetCurrentMap();
    s.keyframes = static_cast<long>(atlas->KeyFramesInMap());
    f.imu_init = atlas->isImuInitialized();
    f.map_id = map ? static_cast<std::int64_t>(map->GetId()) : 0;
    f.imu_ba2 = f.imu_init && map && map->GetIniertialBA2();
    f.has_pose = frame.isSet();
    f.n_extracted = frame.N;
    f.n_inliers = s.n_inliers;
    f.n_frustum = s.n_frustum;
    jsve::fill_bins_from_grid(f, [&](int c, int r) { return frame.mGrid[c][r].size(); });
    if (f.has_pose) {
        copy3(f.vis_p, frame.GetImuPosition());
        copy_quaternion(f.vis_q, frame.GetImuRotation());
        if (frame.HasVelocity()) copy3(f.vis_v, frame.GetVelocity());
        // A NaN pose (the same broken IMU initialisation, before the reset) is no pose: logged as the
        // frame without one above (LOST in a tracking state), counted, never a refused row.
        bool finite = true;
        for (int i = 0; i < 3; ++i) finite = finite && std::isfinite(f.vis_p[i]) && std::isfinite(f.vis_v[i]);
        for (int i = 0; i < 4; ++i) finite = finite && std::isfinite(f.vis_q[i]);
        if (!finite) {
            f.has_pose = false;
            if (f.state == 2 || f.state == 3 || f.state == 5) f.state = 4;
            ++s.pose_invalid_frames;
        }
    }
    // The world frame of the map now (a re-expression by LocalMapping while Track() ran may or may not
    // have reached this frame's pose yet: at most the frame it happens at is off).
    const Similarity world = world_frame(f.map_id);
    for (int i = 0; i < 4; ++i) f.world_q[i] = world.q[i];
    for (int i = 0; i < 3; ++i) f.world_t[i] = world.t[i];
    f.world_s = world.s;
    // The log's first frame carries no preintegration (the format's rule), nor does the first frame
    // after a reset or a new map (integrated from an uninitialised stamp: see HookState); later
    // frames the one from the previous frame, corrected to this frame's bias estimate.
    // A failed IMU initialisation leaves NaN in the bias estimate or in the preintegration itself
    // (LocalMapping then flags it and ORB-SLAM3 resets the map): correcting to a NaN bias makes Sophus
    // abort the process (SO3::exp of NaN), so such a frame carries the preintegration at the bias it
    // was integrated with, and a preintegration that is NaN itself is logged as none (imu_dt 0,
    // identity), counted in `imu_invalid_frames` (the driver's summary): never a crash of the hook's.
    ORB_SLAM3::IMU::Preintegrated* pre = frame.mpImuPreintegratedFrame;
    if (s.log->frames() > 0 && pre != nullptr && !s.previous_frame_cleared) {
        const ORB_SLAM3::IMU::Bias& b = frame.mImuBias;
        const ORB_SLAM3::IMU::Bias o = pre->GetOriginalBias();
        const float bias[12] = {b.bax, b.bay, b.baz, b.bwx, b.bwy, b.bwz, o.bax, o.bay, o.baz, o.bwx, o.bwy, o.bwz};
        // (the Jacobians too: a NaN JRg makes GetDeltaRotation's SO3::exp abort as a NaN bias does)
        const bool finite = std::all_of(bias, bias + 12, [](float x) { return std::isfinite(x); }) &&
                            pre->JRg.allFinite() && pre->JVg.allFinite() && pre->JVa.allFinite() &&
                            pre->JPg.allFinite() && pre->JPa.allFinite();
        f.imu_dt = pre->dT;
        if (finite) {
            copy3(f.imu_dp, pre->GetDeltaPosition(b));
            copy3(f.imu_dv, pre->GetDeltaVelocity(b));
            copy_quaternion(f.imu_dq, pre->GetDeltaRotation(b));
        } else {
            copy3(f.imu_dp, pre->GetOriginalDeltaPosition());
            copy3(f.imu_dv, pre->GetOriginalDeltaVelocity());
            copy_quaternion(f.imu_dq, pre->GetOriginalDeltaRotation());
        }
        const double* values[4] = {&f.imu_dt, f.imu_dp, f.imu_dv, f.imu_dq};
        const int sizes[4] = {1, 3, 3, 4};
        bool valid = true;
        for (int g = 0; g < 4; ++g)
            for (int i = 0; i < sizes[g]; ++i) valid = valid && std::isfinite(values[g][i]);
        if (!valid) {
            f.imu_dt = 0.0;
            for (int i = 0; i < 3; ++i) f.imu_dp[i] = f.imu_dv[i] = 0.0;
            f.imu_dq[0] = 1.0, f.imu_dq[1] = f.imu_dq[2] = f.imu_dq[3] = 0.0;
            ++s.imu_invalid_frames;
        }
    }
    const jsve::Status status = s.log->write(f);
    if (status != jsve::Status::kOk) throw jsve::LogError(status, s.log->last_error());
    MaskState& m = mask_state();
    if (m.on) {
        m.t_ns.push_back(f.t_ns);
        m.before.push_back(m.n_before);
        m.removed.push_back(m.n_removed);
        m.n_before = m.n_removed = 0;
    }
    log_keypoints(frame, f.t_ns, f.n_inliers, image_width, image_height);
    s.log_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// JSON text of [qw, qx, qy, qz, tx, ty, tz] (shortest round-trip doubles).
inline void append_pose(std::string& out, const Sophus::SE3f& pose) {
    double q[4], t[3];
    copy_pose(q, t, pose);
    out += '[';
    for (int i = 0; i < 7; ++i) {
        if (i) out += ',';
        out += jsve::detail::double_text(i < 4 ? q[i] : t[i - 4]);
    }
    out += ']';
}

template <class Values, class Put>
void append_list(std::string& out, const char* key, const Values& values, Put&& put, bool last = false) {
    out += '"';
    out += key;
    out += "\":[";
    bool first = true;
    for (const auto& v : values) {
        if (!first) out += ',';
        first = false;
        put(out, v);
    }
    out += last ? "]" : "],";
}

// Waits (up to `timeout_s`) until LocalMapping and LoopClosing have finished, as System::Shutdown
// requests, and no global BA runs: the keyframes then hold their final poses.
inline bool wait_idle(const TrackerView& v, double timeout_s) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (!v.local_mapping->isFinished() || !v.loop_closing->isFinished() || v.loop_closing->isRunningGBA()) {
        if (std::chrono::steady_clock::now() > until) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return true;
}

bool write_trailer(double timeout_s, std::string* error) {
    HookState& s = state();
    const TrackerView v = tracker_view();
    auto refuse = [&](const std::string& why) {
        s.trailer_error = why;
        if (error) *error = why;
        return false;
    };
    if (!s.log || v.atlas == nullptr) return refuse("no frame was logged");
    if (!wait_idle(v, timeout_s)) return refuse("LocalMapping or LoopClosing did not finish in time");
    if (s.entry_rows.size() != v.relative->size())
        return refuse("the trajectory has " + std::to_string(v.relative->size()) + " entries, the hook saw " +
                      std::to_string(s.entry_rows.size()));
    // Every keyframe the trajectory references, and the parents SaveTrajectoryEuRoC walks from a bad one.
    std::set<ORB_SLAM3::KeyFrame*, bool (*)(ORB_SLAM3::KeyFrame*, ORB_SLAM3::KeyFrame*)> keyframes(
        [](ORB_SLAM3::KeyFrame* a, ORB_SLAM3::KeyFrame* b) { return a->mnId < b->mnId; });
    std::vector<ORB_SLAM3::KeyFrame*> named(v.references->begin(), v.references->end());
    named.insert(named.end(), logged_references().begin(), logged_references().end());
    for (ORB_SLAM3::KeyFrame* kf : named) {
        for (int depth = 0; kf != nullptr && depth < 100000 && keyframes.insert(kf).second; ++depth)
            kf = kf->isBad() ? kf->GetParent() : nullptr;
    }
    std::vector<ORB_SLAM3::Map*> maps = v.atlas->GetAllMaps();  // SaveTrajectoryEuRoC's order (by id)
    for (ORB_SLAM3::Map* m : maps) {
        const std::vector<ORB_SLAM3::KeyFrame*> all = m->GetAllKeyFrames();
        if (!all.empty()) keyframes.insert(*std::min_element(all.begin(), all.end(), ORB_SLAM3::KeyFrame::lId));
    }
    std::vector<ORB_SLAM3::KeyFrame*> kfs(keyframes.begin(), keyframes.end());
    std::string out = "{";
    const Sophus::SE3f t_bc = kfs.empty() ? Sophus::SE3f() : kfs.front()->mImuCalib.mTbc;
    out += "\"t_bc\":";
    append_pose(out, t_bc);
    out += ",\"maps\":{";
    append_list(out, "id", maps, [](std::string& o, ORB_SLAM3::Map* m) { o += std::to_string(m->GetId()); });
    append_list(out, "keyframes", maps,
                [](std::string& o, ORB_SLAM3::Map* m) { o += std::to_string(m->GetAllKeyFrames().size()); }, true);
    out += "},\"keyframes\":{";
    auto map_of = [](ORB_SLAM3::KeyFrame* kf) {
        ORB_SLAM3::Map* m = kf->GetMap();
        return m == nullptr ? std::string("-1") : std::to_string(m->GetId());
    };
    append_list(out, "id", kfs, [](std::string& o, ORB_SLAM3::KeyFrame* kf) { o += std::to_string(kf->mnId); });
    append_list(out, "map_id", kfs, [&](std::string& o, ORB_SLAM3::KeyFrame* kf) { o += map_of(kf); });
    append_list(out, "bad", kfs, [](std::string& o, ORB_SLAM3::KeyFrame* kf) { o += kf->isBad() ? "1" : "0"; });
    append_list(out, "parent", kfs, [](std::string& o, ORB_SLAM3::KeyFrame* kf) {
        ORB_SLAM3::KeyFrame* p = kf->GetParent();
        o += p == nullptr ? std::string("-1") : std::to_string(p->mnId);
    });
    append_list(out, "t_cw", kfs, [](std::string& o, ORB_SLAM3::KeyFrame* kf) { append_pose(o, kf->GetPose()); });
    append_list(out, "t_cp", kfs, [](std::string& o, ORB_SLAM3::KeyFrame* kf) { append_pose(o, kf->mTcp); }, true);
    out += "},\"trajectory\":{";
    append_list(out, "row", s.entry_rows, [](std::string& o, std::int64_t r) { o += std::to_string(r); });
    append_list(out, "ref_kf", *v.references, [](std::string& o, ORB_SLAM3::KeyFrame* kf) {
        o += kf == nullptr ? std::string("-1") : std::to_string(kf->mnId);
    });
    append_list(out, "lost", *v.lost, [](std::string& o, bool b) { o += b ? "1" : "0"; });
    append_list(out, "t_cr", *v.relative, [](std::string& o, const Sophus::SE3f& t) { append_pose(o, t); }, true);
    out += "}}";
    if (s.log->trailer("orbslam3", out) != jsve::Status::kOk) return refuse(s.log->last_error());
    return true;
}

}  // namespace jsve_hook

#endif  // JSVE_HOOK_IMPLEMENTATION
