// jsve_log.hpp: header-only C++17 writer of jsve tracking log format v3.
//
// Part of jsve (GPL-3.0-or-later). The format itself is defined in jsve/io/_schema.py and described
// in docs/log-format.md; the hook guide for ORB-SLAM3 v1.0 is docs/frontend.md. This header has no
// dependencies beyond the C++17 standard library, and its interface takes only plain structs and
// arrays (no Eigen, OpenCV or Sophus types), so it drops into any front-end:
//
//     #include "jsve_log.hpp"          // g++ -std=c++17 -I"$(jsve frontend-include)" ...
//
//     jsve::Metadata meta;
//     meta.set("sequence", "MH_04").set("run", 7).set("fps", 20)
//         .set("image_size", {752, 480}).set("gravity", {0.0, 0.0, -9.81});
//     jsve::LogWriter log("logs/MH_04_run7.csv", meta);   // writes logs/MH_04_run7.csv.partial
//     for (...each frame...) {
//         jsve::Frame f;                                     // zeros, identity quaternions
//         f.t_ns = stamp_ns; f.state = 2; f.map_id = map_id; ...
//         f.has_pose = false;                                // only outside OK, RECENTLY_LOST, OK_KLT
//         log.write(f);
//     }
//     log.close();                       // end marker, then rename to logs/MH_04_run7.csv
//
// Columns (docs/log-format.md): t_ns, state, imu_init, map_id, imu_ba2, n_extracted, n_inliers,
// n_frustum, bin_0..bin_63, vis_* (10), imu_dt, imu_dp*, imu_dv*, imu_dq* (11), then two optional
// groups, each decided once per log in Options: the seven gt_* (Options::ground_truth; a frame may
// leave them empty, Frame::has_gt) and, last, the eight world_* (Options::world_frame; written on
// every frame): world_qw, world_qx, world_qy, world_qz, world_tx, world_ty, world_tz, world_s, the
// similarity W from the frame's map's first world frame to the world frame its vis_* pose is in,
// x_current = world_s * R(world_q) * x_first + world_t for points (the identity until the front-end
// first re-expresses the map, as ORB-SLAM3's Map::ApplyScaledRotation does without a new map id).
// A third optional group, after those (Options::keyframes): events, traj, ref_kf, rel_px, rel_py,
// rel_pz, rel_qw, rel_qx, rel_qy, rel_qz: the front-end's events at this frame (a bit set of
// Event), whether the frame entered the front-end's saved trajectory, its reference keyframe and its
// camera pose relative to that keyframe's camera (T_cr; empty when ref_kf is -1). Trailer lines
// (`# jsve-log trailer KEY JSON`, LogWriter::trailer) may follow the frames, before the end marker:
// the front-end's state at the end of the run (docs/log-format.md, "Format v3").
//
// Guarantees
//   * A log never looks complete when it is not. Lines go to `<path>.partial`; the end marker
//     (`# jsve-log end frames=N`) is written only by close(), which then renames the file to
//     `<path>`. A crash, a kill, an exception that unwinds past the writer, or a rejected frame
//     leaves only `<path>.partial`, which jsve's reader reports as incomplete.
//   * Doubles are written in the shortest form that reads back to the same bits (at most 17
//     significant digits; std::to_chars where the library has it, else snprintf "%.17g"),
//     independent of the C and C++ locales; float columns always carry a '.' or an exponent
//     ("1.0", "-0.0", "1e-300"). Integers are exact (int64 stamps).
//   * Buffered output is flushed every Options::flush_every frames (default 100) and at close.
//     flush means fflush (the data reaches the operating system, which survives a process crash;
//     surviving a power cut would need fsync, which this header does not call).
//
// Error policy (Options::on_error)
//   * OnError::kThrow (default): any call that would return a non-OK Status throws jsve::LogError
//     (a std::runtime_error carrying the Status) instead.
//   * OnError::kReturn: calls return the Status; last_error() holds the message.
//   A frame that jsve's reader would reject (a non-finite double, a stamp not after the previous
//   one, a state outside -1..5, a negative map_id, imu_ba2 without imu_init, no pose in state OK,
//   RECENTLY_LOST or OK_KLT, a negative count, more binned keypoints or inliers than extracted
//   keypoints, a quaternion whose norm is off 1 by more than 1e-6, a negative imu_dt, a first frame
//   with a preintegration that is not zero / identity, with world_frame a world_s that is not
//   positive) is never written, and it marks the writer as failed: every later write() and close()
//   reports Status::kFailed, close() leaves `<path>.partial` in place, and the run shows up as
//   incomplete rather than silently missing a frame. To repair a frame instead, call check(frame)
//   first; it validates without writing and without changing the writer. abandon() (also run by
//   the destructor of an open writer) closes the file and leaves it as `.partial`; it never throws.
//   open() checks the metadata the same way (required keys sequence/run/fps, the types and values
//   jsve.io._logs accepts for the keys it knows) and creates no file when it is wrong; close() before
//   any frame reports Status::kNoFrames, since a log has at least one frame.
//
// Not thread-safe: use one writer per run from one thread (ORB-SLAM3's tracking thread).

#ifndef JSVE_LOG_HPP
#define JSVE_LOG_HPP

#include <cerrno>
#include <charconv>
#include <clocale>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <initializer_list>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>
#if defined(__unix__) || defined(__APPLE__)
#include <fcntl.h>
#include <unistd.h>
#endif

#if !defined(JSVE_LOG_USE_SNPRINTF) && defined(__cpp_lib_to_chars) && __cpp_lib_to_chars >= 201611L
#define JSVE_LOG_HAVE_FP_TO_CHARS 1
#else
#define JSVE_LOG_HAVE_FP_TO_CHARS 0
#endif

namespace jsve {

inline constexpr int kFormatVersion = 3;
inline constexpr double kFloatMax = 3.4028234663852886e38;  // float32's largest: jsve.io._schema.FLOAT_MAX
inline constexpr int kBinMax = 65535;                        // uint16: jsve.io._schema.BIN_MAX
inline constexpr int kBins = 64;          // SVE bins per frame, 8 x 8, row-major (k = 8 * by + bx)
inline constexpr int kGridCols = 64;      // ORB-SLAM3 FRAME_GRID_COLS
inline constexpr int kGridRows = 48;      // ORB-SLAM3 FRAME_GRID_ROWS
inline constexpr const char* kMagic = "# jsve-log v3 ";
inline constexpr const char* kTrailerPrefix = "# jsve-log trailer ";
inline constexpr const char* kEndMarker = "# jsve-log end frames=";
inline constexpr const char* kPartialSuffix = ".partial";
inline constexpr double kUnitQuaternionTolerance = 1e-6;  // schema.UNIT_QUATERNION_TOLERANCE

enum class Status : int {
    kOk = 0,
    kNotOpen,              // write()/close() on a writer that is not open
    kAlreadyOpen,          // open() on a writer that is open
    kExists,               // `<path>` exists and Options::overwrite is false
    kIoError,              // fopen/fwrite/fflush/fclose/rename failed (errno text in the message)
    kBadMetadata,          // a metadata value or a required key is missing or of the wrong type
    kNonFinite,            // a NaN or infinite double in a frame
    kNonIncreasingStamp,   // t_ns not strictly after the previous frame's
    kOutOfRange,           // state, map_id, imu_ba2, missing pose, counts, bins, quaternion norm, imu_*,
                           // world_s, a double beyond float32's range
    kNoFrames,             // close() before any frame: a log has at least one
    kFailed,               // the writer failed earlier; nothing more is written
};

inline const char* to_string(Status s) noexcept {
    switch (s) {
        case Status::kOk: return "ok";
        case Status::kNotOpen: return "not open";
        case Status::kAlreadyOpen: return "already open";
        case Status::kExists: return "file exists";
        case Status::kIoError: return "I/O error";
        case Status::kBadMetadata: return "bad metadata";
        case Status::kNonFinite: return "non-finite value";
        case Status::kNonIncreasingStamp: return "non-increasing stamp";
        case Status::kOutOfRange: return "value out of range";
        case Status::kNoFrames: return "no frames";
        case Status::kFailed: return "writer failed earlier";
    }
    return "unknown";
}

class LogError : public std::runtime_error {
public:
    LogError(Status status, const std::string& message) : std::runtime_error(message), status_(status) {}
    Status status() const noexcept { return status_; }

private:
    Status status_;
};

enum class OnError { kThrow, kReturn };

struct Options {
    bool ground_truth = false;   // add the seven gt_* columns (decided once per log)
    bool world_frame = false;    // add the eight world_* columns (decided once per log)
    bool keyframes = false;      // add the ten keyframe columns, last: events, traj, ref_kf, rel_* (once per log)
    int flush_every = 100;       // fflush after every N frames; 0 or less: only at close
    bool overwrite = false;      // replace an existing `<path>` (removed at open, not at close)
    OnError on_error = OnError::kThrow;
};

// One frame, in the units of docs/log-format.md. Defaults: zeros, identity quaternions, a pose,
// map 0.
struct Frame {
    std::int64_t t_ns = 0;          // sensor stamp, nanoseconds
    int state = 0;                  // ORB-SLAM3 Tracking::eTrackingState, -1..5
    bool imu_init = false;          // Atlas::isImuInitialized() for the active map
    std::int64_t map_id = 0;        // mpAtlas->GetCurrentMap()->GetId(), >= 0
    bool imu_ba2 = false;           // mpAtlas->GetCurrentMap()->GetIniertialBA2(); needs imu_init
    bool has_pose = true;           // mCurrentFrame.isSet(); false (only outside states 2, 3, 5):
                                    // the ten vis_* fields are left empty and not checked
    int n_extracted = 0;            // Frame::N
    int n_inliers = 0;              // Tracking::mnMatchesInliers after TrackLocalMap
    int n_frustum = 0;              // nToMatch in Tracking::SearchLocalPoints
    int bins[kBins] = {};           // keypoints per SVE bin (see fill_bins_from_grid)
    double vis_p[3] = {0.0, 0.0, 0.0};       // body position, world frame, m
    double vis_q[4] = {1.0, 0.0, 0.0, 0.0};  // body-to-world rotation, wxyz
    double vis_v[3] = {0.0, 0.0, 0.0};       // body velocity, world frame, m/s
    double imu_dt = 0.0;                     // preintegration interval, s (0 on the first frame)
    double imu_dp[3] = {0.0, 0.0, 0.0};      // preintegrated position delta, previous body frame, m
    double imu_dv[3] = {0.0, 0.0, 0.0};      // preintegrated velocity delta, previous body frame, m/s
    double imu_dq[4] = {1.0, 0.0, 0.0, 0.0}; // preintegrated rotation delta, wxyz
    bool has_gt = true;                      // false: this frame's gt_* fields are left empty
    double gt_p[3] = {0.0, 0.0, 0.0};        // ground-truth body position (only with ground_truth)
    double gt_q[4] = {1.0, 0.0, 0.0, 0.0};   // ground-truth body-to-world rotation, wxyz
    double world_q[4] = {1.0, 0.0, 0.0, 0.0}; // rotation of the similarity from the map's first world
                                              // frame to this frame's (only with world_frame), wxyz
    double world_t[3] = {0.0, 0.0, 0.0};     // its translation, m (this frame's world)
    double world_s = 1.0;                    // its scale, > 0, dimensionless; all three written on
                                             // every frame, with or without a pose
    std::uint32_t events = 0;                // bit set of Event at this frame (only with keyframes)
    bool traj = false;                       // the frame entered the saved trajectory (needs ref_kf >= 0)
    std::int64_t ref_kf = -1;                // reference keyframe id, -1: none (rel_* left empty)
    double rel_p[3] = {0.0, 0.0, 0.0};       // T_cr translation: camera relative to the reference
    double rel_q[4] = {1.0, 0.0, 0.0, 0.0};  // keyframe's camera (m, wxyz); ORB-SLAM3's mlRelativeFramePoses
};

// Front-end events, the bits of Frame::events (jsve.io._schema.EVENTS): each set on the first frame
// logged after it happened (events of other threads, as ORB-SLAM3's LocalMapping and LoopClosing, are
// collected until the next frame).
enum Event : std::uint32_t {
    kEventReset = 1u << 0,       // the active map was reset (Tracking::ResetActiveMap)
    kEventResetAll = 1u << 1,    // every map was reset (Tracking::Reset)
    kEventNewMap = 1u << 2,      // a new map was started (Tracking::CreateMapInAtlas)
    kEventMerge = 1u << 3,       // two maps were merged (LoopClosing::MergeLocal, MergeLocal2)
    kEventLoop = 1u << 4,        // a loop was closed (LoopClosing::CorrectLoop)
    kEventImuInit = 1u << 5,     // the map's IMU was initialised (Map::SetImuInitialized, first time)
    kEventBa1 = 1u << 6,         // the map's inertial BA1 ran (Map::SetIniertialBA1, first time)
    kEventBa2 = 1u << 7,         // the map's inertial BA2 ran (Map::SetIniertialBA2, first time)
};
inline constexpr std::uint32_t kEventMask = (1u << 8) - 1;

// SVE bin of an ORB-SLAM3 grid cell: bin x = col / 8, bin y = row / 6, k = 8 * y + x.
constexpr int bin_of_cell(int col, int row) noexcept { return 8 * (row / 6) + col / 8; }

// Fills f.bins from ORB-SLAM3's 64 x 48 keypoint grid; count(col, row) returns the number of
// keypoints in cell (col, row), e.g. [&](int c, int r) { return int(frame.mGrid[c][r].size()); }.
template <class CountFn>
void fill_bins_from_grid(Frame& f, CountFn&& count) {
    static_assert(kGridCols == 8 * 8 && kGridRows == 8 * 6, "8 x 8 bins of 8 x 6 cells");
    for (int k = 0; k < kBins; ++k) f.bins[k] = 0;
    for (int col = 0; col < kGridCols; ++col) {
        for (int by = 0; by < 8; ++by) {
            int sum = 0;  // one store per 6 cells: a store per cell serialises on bins[k]
            for (int row = 6 * by; row < 6 * by + 6; ++row) sum += static_cast<int>(count(col, row));
            f.bins[bin_of_cell(col, 6 * by)] += sum;
        }
    }
}

namespace detail {

// snprintf follows LC_NUMERIC; the file must not: the locale's decimal separator in [p, q) becomes '.'.
inline char* c_decimal_point(char* p, char* q) {
    const char* dp = std::localeconv()->decimal_point;
    const std::size_t dn = std::strlen(dp);
    if (dn > 0 && !(dn == 1 && dp[0] == '.')) {
        for (char* s = p; s + dn <= q; ++s) {
            if (std::memcmp(s, dp, dn) == 0) {
                *s = '.';
                std::memmove(s + 1, s + dn, static_cast<std::size_t>(q - (s + dn)));
                return q - (dn - 1);
            }
        }
    }
    return q;
}

// Number text [p, q) marked as a float: ".0" appended unless it has '.', an exponent, or is inf/nan.
inline char* float_marked(char* p, char* q) {
    for (const char* s = p; s < q; ++s)
        if (*s == '.' || *s == 'e' || *s == 'E' || *s == 'n' || *s == 'i') return q;
    q[0] = '.';
    q[1] = '0';
    return q + 2;
}

// Shortest round-trip text of a double; always contains '.', 'e' (or is "inf"/"nan", which the
// writer never emits). Needs 26 chars at most.
inline char* put_double(char* p, char* end, double v) {
#if JSVE_LOG_HAVE_FP_TO_CHARS
    return float_marked(p, std::to_chars(p, end, v).ptr);
#else
    const int n = std::snprintf(p, static_cast<std::size_t>(end - p), "%.17g", v);
    return float_marked(p, c_decimal_point(p, p + n));
#endif
}

// Text of a float that reads back, rounded to float, to the same bits: the shortest such text, or
// "%.9g" (9 significant digits hold every float) without std::to_chars; marked as put_double's.
// Needs 18 chars at most.
inline char* put_float(char* p, char* end, float v) {
#if JSVE_LOG_HAVE_FP_TO_CHARS
    return float_marked(p, std::to_chars(p, end, v).ptr);
#else
    const int n = std::snprintf(p, static_cast<std::size_t>(end - p), "%.9g", static_cast<double>(v));
    return float_marked(p, c_decimal_point(p, p + n));
#endif
}

inline char* put_int(char* p, char* end, std::int64_t v) { return std::to_chars(p, end, v).ptr; }

inline std::string double_text(double v) {
    char buf[32];
    return std::string(buf, put_double(buf, buf + sizeof buf, v));
}

inline bool valid_utf8(const std::string& s) {
    const auto* u = reinterpret_cast<const unsigned char*>(s.data());
    const std::size_t n = s.size();
    std::size_t i = 0;
    while (i < n) {
        const unsigned c = u[i];
        std::size_t len;
        std::uint32_t cp;
        if (c < 0x80) { ++i; continue; }
        if ((c & 0xE0) == 0xC0) { len = 2; cp = c & 0x1F; }
        else if ((c & 0xF0) == 0xE0) { len = 3; cp = c & 0x0F; }
        else if ((c & 0xF8) == 0xF0) { len = 4; cp = c & 0x07; }
        else return false;
        if (i + len > n) return false;
        for (std::size_t k = 1; k < len; ++k) {
            if ((u[i + k] & 0xC0) != 0x80) return false;
            cp = (cp << 6) | (u[i + k] & 0x3F);
        }
        if ((len == 2 && cp < 0x80) || (len == 3 && cp < 0x800) || (len == 4 && cp < 0x10000)) return false;
        if (cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF)) return false;
        i += len;
    }
    return true;
}

inline void append_json_string(std::string& out, const std::string& s) {
    static const char hex[] = "0123456789abcdef";
    out += '"';
    for (const char ch : s) {
        const auto c = static_cast<unsigned char>(ch);
        switch (c) {
            case '"': out += "\\\""; break;
            case '\\': out += "\\\\"; break;
            case '\n': out += "\\n"; break;
            case '\r': out += "\\r"; break;
            case '\t': out += "\\t"; break;
            case '\b': out += "\\b"; break;
            case '\f': out += "\\f"; break;
            default:
                if (c < 0x20 || c == 0x7F) {
                    out += "\\u00";
                    out += hex[c >> 4];
                    out += hex[c & 0xF];
                } else {
                    out += ch;
                }
        }
    }
    out += '"';
}

}  // namespace detail

// Metadata for line 1, kept in insertion order; set() on an existing key replaces its value.
// Values: strings (UTF-8), integers (int64), finite doubles, and arrays of integers or doubles.
// An invalid value (non-finite double, invalid UTF-8, integer above INT64_MAX, empty key) is
// remembered and reported by LogWriter::open() as Status::kBadMetadata.
class Metadata {
public:
    enum class Kind { kString, kInt, kDouble, kIntArray, kDoubleArray };

    Metadata& set(const std::string& key, const std::string& value) {
        if (!detail::valid_utf8(value)) return invalid(key, "string is not valid UTF-8");
        std::string json;
        detail::append_json_string(json, value);
        return put(key, Kind::kString, std::move(json));
    }
    Metadata& set(const std::string& key, const char* value) {
        if (value == nullptr) return invalid(key, "null string");
        return set(key, std::string(value));
    }
    template <class T, std::enable_if_t<std::is_integral_v<T>, int> = 0>
    Metadata& set(const std::string& key, T value) {
        static_assert(!std::is_same_v<T, bool>, "jsve metadata has no booleans: use 0/1");
        std::int64_t v;
        if (!to_int64(value, v)) return invalid(key, "integer does not fit in int64");
        char buf[24];
        return put(key, Kind::kInt, std::string(buf, detail::put_int(buf, buf + sizeof buf, v)), {static_cast<double>(v)});
    }
    template <class T, std::enable_if_t<std::is_floating_point_v<T>, int> = 0>
    Metadata& set(const std::string& key, T value) {
        const double v = static_cast<double>(value);
        if (!std::isfinite(v)) return invalid(key, "double is not finite (JSON has no NaN or infinity)");
        return put(key, Kind::kDouble, detail::double_text(v), {v});
    }
    template <class T>
    Metadata& set(const std::string& key, std::initializer_list<T> values) {
        return set_array(key, values.begin(), values.size());
    }
    template <class T>
    Metadata& set(const std::string& key, const std::vector<T>& values) {
        return set_array(key, values.data(), values.size());
    }
    template <class T>
    Metadata& set_array(const std::string& key, const T* data, std::size_t n) {
        static_assert(std::is_arithmetic_v<T> && !std::is_same_v<T, bool>, "arrays of integers or doubles");
        std::string json = "[";
        std::vector<double> nums;
        nums.reserve(n);
        for (std::size_t i = 0; i < n; ++i) {
            if (i) json += ", ";
            if constexpr (std::is_integral_v<T>) {
                std::int64_t v;
                if (!to_int64(data[i], v)) return invalid(key, "integer does not fit in int64");
                char buf[24];
                json.append(buf, detail::put_int(buf, buf + sizeof buf, v));
                nums.push_back(static_cast<double>(v));
            } else {
                const double v = static_cast<double>(data[i]);
                if (!std::isfinite(v)) return invalid(key, "double is not finite (JSON has no NaN or infinity)");
                json += detail::double_text(v);
                nums.push_back(v);
            }
        }
        json += "]";
        return put(key, std::is_integral_v<T> ? Kind::kIntArray : Kind::kDoubleArray, std::move(json), std::move(nums));
    }

    bool has(const std::string& key) const { return find(key) != nullptr; }
    // Kind of a key's value; false when the key is absent.
    bool kind(const std::string& key, Kind& out) const {
        const Entry* e = find(key);
        if (e) out = e->kind;
        return e != nullptr;
    }
    // The numbers of a numeric value or array (integers as doubles); false when absent or a string.
    bool numbers(const std::string& key, std::vector<double>& out) const {
        const Entry* e = find(key);
        if (e == nullptr || e->kind == Kind::kString) return false;
        out = e->nums;
        return true;
    }
    // First invalid value set, or an empty string.
    const std::string& error() const { return error_; }

    // The JSON object of line 1, e.g. {"sequence": "MH_04", "run": 7}.
    std::string to_json() const {
        std::string out = "{";
        for (std::size_t i = 0; i < entries_.size(); ++i) {
            if (i) out += ", ";
            detail::append_json_string(out, entries_[i].key);
            out += ": ";
            out += entries_[i].json;
        }
        out += "}";
        return out;
    }

private:
    struct Entry {
        std::string key;
        Kind kind;
        std::string json;
        std::vector<double> nums;
    };

    template <class T>
    static bool to_int64(T value, std::int64_t& out) {
        if constexpr (std::is_unsigned_v<T>) {
            if (static_cast<std::uint64_t>(value) > static_cast<std::uint64_t>(std::numeric_limits<std::int64_t>::max()))
                return false;
        }
        out = static_cast<std::int64_t>(value);
        return true;
    }
    const Entry* find(const std::string& key) const {
        for (const Entry& e : entries_)
            if (e.key == key) return &e;
        return nullptr;
    }
    Metadata& invalid(const std::string& key, const char* why) {
        if (error_.empty()) error_ = "metadata \"" + key + "\": " + why;
        return *this;
    }
    Metadata& put(const std::string& key, Kind kind, std::string json, std::vector<double> nums = {}) {
        if (key.empty()) return invalid(key, "empty key");
        if (!detail::valid_utf8(key)) return invalid(key, "key is not valid UTF-8");
        for (Entry& e : entries_) {
            if (e.key == key) {
                e.kind = kind;
                e.json = std::move(json);
                e.nums = std::move(nums);
                return *this;
            }
        }
        entries_.push_back(Entry{key, kind, std::move(json), std::move(nums)});
        return *this;
    }

    std::vector<Entry> entries_;
    std::string error_;
};

class LogWriter {
public:
    LogWriter() = default;
    // Opens at once; see open().
    LogWriter(const std::string& path, const Metadata& meta, const Options& options = Options()) {
        open(path, meta, options);
    }
    ~LogWriter() { abandon(); }

    LogWriter(const LogWriter&) = delete;
    LogWriter& operator=(const LogWriter&) = delete;
    LogWriter(LogWriter&& other) noexcept { take(other); }
    LogWriter& operator=(LogWriter&& other) noexcept {
        if (this != &other) {
            abandon();
            take(other);
        }
        return *this;
    }

    // Validates the metadata, creates `<path>.partial` (truncating a stale one), writes line 1
    // (magic + metadata JSON) and the header row, and flushes them. `<path>` itself must not
    // exist unless options.overwrite, in which case it is removed now, so that a crash of this
    // run can never leave an older complete log beside the new `.partial`.
    Status open(const std::string& path, const Metadata& meta, const Options& options = Options()) {
        if (file_ != nullptr)
            return fail(Status::kAlreadyOpen, "open(\"" + path + "\"): already writing " + partial_, options.on_error);
        options_ = options;
        failed_ = Status::kOk;
        error_.clear();
        frames_ = 0;
        trailers_ = 0;
        have_last_ = false;
        path_ = path;
        partial_ = path + kPartialSuffix;
        if (path.empty()) return fail(Status::kIoError, "open(): empty path");
        std::string why;
        if (!check_metadata(meta, why)) return fail(Status::kBadMetadata, path + ": " + why);
        if (std::FILE* existing = std::fopen(path.c_str(), "rb")) {
            std::fclose(existing);
            if (!options_.overwrite)
                return fail(Status::kExists, path + ": exists (set Options::overwrite to replace it)");
            if (std::remove(path.c_str()) != 0) return fail(Status::kIoError, path + ": cannot remove: " + errno_text());
        }
        file_ = std::fopen(partial_.c_str(), "wb");
        if (file_ == nullptr) return fail(Status::kIoError, partial_ + ": cannot create: " + errno_text());
        // Our own buffer: glibc ignores the size of setvbuf when it allocates the buffer itself.
        if (!buffer_) buffer_.reset(new char[kBufferSize]);
        std::setvbuf(file_, buffer_.get(), _IOFBF, kBufferSize);
        std::string head = kMagic;
        head += meta.to_json();
        head += '\n';
        append_header_row(head, options_.ground_truth, options_.world_frame, options_.keyframes);
        if (std::fwrite(head.data(), 1, head.size(), file_) != head.size() || std::fflush(file_) != 0)
            return io_failure("cannot write the header");
        return Status::kOk;
    }

    // Validates one frame without writing it and without changing the writer (never throws).
    // Checks what jsve's reader rejects; `why`, when given, receives the reason.
    Status check(const Frame& f, std::string* why = nullptr) const {
        std::string msg;
        const Status s = validate(f, msg);
        if (why) *why = msg;
        return s;
    }

    // Validates and appends one frame. A rejected frame is not written and fails the writer
    // (see the error policy at the top of this file).
    Status write(const Frame& f) {
        if (file_ == nullptr) return fail(Status::kNotOpen, "write(): the writer is not open");
        if (failed_ != Status::kOk) return fail(Status::kFailed, partial_ + ": writer failed earlier: " + error_);
        if (trailers_ > 0) {
            failed_ = Status::kOutOfRange;
            return fail(Status::kOutOfRange, partial_ + ": frame " + std::to_string(frames_) + " after a trailer line");
        }
        std::string msg;
        const Status s = validate(f, msg);
        if (s != Status::kOk) {
            failed_ = s;
            return fail(s, partial_ + ": frame " + std::to_string(frames_) + " rejected: " + msg);
        }
        char line[kLineCapacity];
        char* const end = line + sizeof line;
        char* p = line;
        p = detail::put_int(p, end, f.t_ns);
        *p++ = ',';
        p = detail::put_int(p, end, f.state);
        *p++ = ',';
        *p++ = f.imu_init ? '1' : '0';
        *p++ = ',';
        p = detail::put_int(p, end, f.map_id);
        *p++ = ',';
        *p++ = f.imu_ba2 ? '1' : '0';
        *p++ = ',';
        p = detail::put_int(p, end, f.n_extracted);
        *p++ = ',';
        p = detail::put_int(p, end, f.n_inliers);
        *p++ = ',';
        p = detail::put_int(p, end, f.n_frustum);
        for (int k = 0; k < kBins; ++k) {
            *p++ = ',';
            p = detail::put_int(p, end, f.bins[k]);
        }
        if (f.has_pose) {
            p = put_doubles(p, end, f.vis_p, 3);
            p = put_doubles(p, end, f.vis_q, 4);
            p = put_doubles(p, end, f.vis_v, 3);
        } else {
            for (int i = 0; i < 10; ++i) *p++ = ',';
        }
        p = put_doubles(p, end, &f.imu_dt, 1);
        p = put_doubles(p, end, f.imu_dp, 3);
        p = put_doubles(p, end, f.imu_dv, 3);
        p = put_doubles(p, end, f.imu_dq, 4);
        if (options_.ground_truth) {
            if (f.has_gt) {
                p = put_doubles(p, end, f.gt_p, 3);
                p = put_doubles(p, end, f.gt_q, 4);
            } else {
                for (int i = 0; i < 7; ++i) *p++ = ',';
            }
        }
        if (options_.world_frame) {
            p = put_doubles(p, end, f.world_q, 4);
            p = put_doubles(p, end, f.world_t, 3);
            p = put_doubles(p, end, &f.world_s, 1);
        }
        if (options_.keyframes) {
            *p++ = ',';
            p = detail::put_int(p, end, f.events);
            *p++ = ',';
            *p++ = f.traj ? '1' : '0';
            *p++ = ',';
            p = detail::put_int(p, end, f.ref_kf);
            if (f.ref_kf >= 0) {
                p = put_doubles(p, end, f.rel_p, 3);
                p = put_doubles(p, end, f.rel_q, 4);
            } else {
                for (int i = 0; i < 7; ++i) *p++ = ',';
            }
        }
        *p++ = '\n';
        const auto n = static_cast<std::size_t>(p - line);
        if (std::fwrite(line, 1, n, file_) != n) return io_failure("cannot write frame " + std::to_string(frames_));
        ++frames_;
        last_t_ns_ = f.t_ns;
        have_last_ = true;
        if (options_.flush_every > 0 && frames_ % options_.flush_every == 0 && std::fflush(file_) != 0)
            return io_failure("cannot flush after frame " + std::to_string(frames_ - 1));
        return Status::kOk;
    }

    // Appends the trailer line `# jsve-log trailer KEY JSON` after the frames (no frame may follow):
    // KEY is lower-case letters, digits and '_', `json` one JSON value on one line (the caller's text,
    // written as given: jsve's reader checks it). A refused trailer fails the writer, as a frame does.
    Status trailer(const std::string& key, const std::string& json) {
        if (file_ == nullptr) return fail(Status::kNotOpen, "trailer(): the writer is not open");
        if (failed_ != Status::kOk) return fail(Status::kFailed, partial_ + ": writer failed earlier: " + error_);
        bool key_ok = !key.empty();
        for (char c : key) key_ok = key_ok && ((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_');
        const bool one_line = !json.empty() && json.find('\n') == std::string::npos && json.find('\r') == std::string::npos;
        if (!key_ok || !one_line || frames_ == 0) {
            failed_ = Status::kOutOfRange;
            return fail(Status::kOutOfRange, partial_ + ": trailer '" + key + "' refused: " +
                        (frames_ == 0 ? "no frames before it" : !key_ok ? "KEY must be [a-z0-9_]+" : "JSON must be one non-empty line"));
        }
        std::string line = kTrailerPrefix;
        line += key;
        line += ' ';
        line += json;
        line += '\n';
        if (std::fwrite(line.data(), 1, line.size(), file_) != line.size() || std::fflush(file_) != 0)
            return io_failure("cannot write trailer " + key);
        ++trailers_;
        return Status::kOk;
    }

    // Writes the end marker, flushes, closes and renames `<path>.partial` to `<path>`. On a
    // failed writer it closes the file, keeps `.partial` and reports Status::kFailed.
    Status close() {
        if (file_ == nullptr) return fail(Status::kNotOpen, "close(): the writer is not open");
        if (failed_ != Status::kOk) {
            abandon();
            return fail(Status::kFailed, partial_ + ": not finalised, the writer failed earlier: " + error_);
        }
        if (frames_ == 0) {
            failed_ = Status::kNoFrames;
            abandon();
            return fail(Status::kNoFrames, partial_ + ": not finalised: no frames were written (a log has at least one)");
        }
        std::string tail = kEndMarker;
        tail += std::to_string(frames_);
        tail += '\n';
        if (std::fwrite(tail.data(), 1, tail.size(), file_) != tail.size() || std::fflush(file_) != 0)
            return io_failure("cannot write the end marker");
        std::FILE* f = file_;
        file_ = nullptr;
        if (std::fclose(f) != 0) {
            failed_ = Status::kIoError;
            return fail(Status::kIoError, partial_ + ": close failed: " + errno_text());
        }
#ifdef _WIN32
        std::remove(path_.c_str());  // rename does not replace an existing file on Windows
#endif
        if (std::rename(partial_.c_str(), path_.c_str()) != 0) {
            failed_ = Status::kIoError;
            return fail(Status::kIoError, partial_ + ": cannot rename to " + path_ + ": " + errno_text());
        }
        return Status::kOk;
    }

    // Writes out what the stdio buffer holds (before fork(): a child must not inherit unwritten lines).
    Status flush() {
        if (file_ == nullptr) return fail(Status::kNotOpen, "flush(): the writer is not open");
        if (std::fflush(file_) != 0) return io_failure("cannot flush");
        return Status::kOk;
    }

    // In a process forked from the writer's (after flush()): the log goes on as a copy at `path`, whose
    // `<path>.partial` starts with every line written so far; the original file is left to the parent.
    // `path` must not exist unless Options::overwrite was set, and must be as long as the current path:
    // the switch then allocates nothing on the heap (a lockstep branch must leave its heap as the
    // parent's, docs/frontend.md). POSIX only. A failure fails the writer.
    Status continue_as(const std::string& path) {
        if (file_ == nullptr) return fail(Status::kNotOpen, "continue_as(): the writer is not open");
        if (failed_ != Status::kOk) return fail(Status::kFailed, partial_ + ": writer failed earlier: " + error_);
        if (path == path_ || path.size() != path_.size())
            return fail(Status::kIoError, "continue_as(\"" + path + "\"): not a new path of the current path's length");
#if defined(__unix__) || defined(__APPLE__)
        char partial[4096];
        if (path.size() + std::strlen(kPartialSuffix) + 1 > sizeof partial)
            return fail(Status::kIoError, "continue_as(): path too long");
        std::snprintf(partial, sizeof partial, "%s%s", path.c_str(), kPartialSuffix);
        if (::access(path.c_str(), F_OK) == 0) {
            if (!options_.overwrite) return fail(Status::kExists, path + ": exists (set Options::overwrite to replace it)");
            if (std::remove(path.c_str()) != 0) return fail(Status::kIoError, path + ": cannot remove: " + errno_text());
        }
        const int source = ::open(partial_.c_str(), O_RDONLY);
        const int copy = ::open(partial, O_WRONLY | O_CREAT | O_TRUNC, 0644);
        bool ok = source >= 0 && copy >= 0;
        char block[1 << 14];
        for (ssize_t n = 0; ok && (n = ::read(source, block, sizeof block)) != 0;)
            ok = n > 0 && ::write(copy, block, static_cast<std::size_t>(n)) == n;
        if (source >= 0) ::close(source);
        if (copy >= 0) ok = ::close(copy) == 0 && ok;
        if (!ok) return io_failure(std::string("cannot copy the log so far to ") + partial);
        // The same FILE on the copy (this process's descriptor of the parent's file is closed).
        if (std::freopen(partial, "ab", file_) == nullptr) {
            file_ = nullptr;
            return io_failure("cannot reopen");
        }
        std::setvbuf(file_, buffer_.get(), _IOFBF, kBufferSize);
        path_.replace(0, path_.size(), path);              // same length: no allocation
        partial_.replace(0, path_.size(), path);
        return Status::kOk;
#else
        return fail(Status::kIoError, "continue_as(\"" + path + "\"): needs fork(), POSIX only");
#endif
    }

    // Closes the file without finalising it: `<path>.partial` stays, reported as incomplete.
    void abandon() noexcept {
        if (file_ != nullptr) {
            std::fflush(file_);
            std::fclose(file_);
            file_ = nullptr;
        }
    }

    bool is_open() const noexcept { return file_ != nullptr; }
    bool failed() const noexcept { return failed_ != Status::kOk; }
    std::int64_t frames() const noexcept { return frames_; }
    const std::string& last_error() const noexcept { return error_; }
    const std::string& path() const noexcept { return path_; }
    const std::string& partial_path() const noexcept { return partial_; }

private:
    static constexpr std::size_t kBufferSize = std::size_t{1} << 16;  // stdio buffer, 64 KiB
    // t_ns, state, imu_init, map_id, imu_ba2, 3 counts, 64 bins at <= 21 chars each; 36 doubles
    // (10 vis_*, 11 imu_*, 7 gt_*, 8 world_*, 7 rel_*) at <= 27 chars; events, traj, ref_kf.
    static constexpr std::size_t kLineCapacity = 11 * 21 + kBins * 21 + 43 * 27 + 16;

    static char* put_doubles(char* p, char* end, const double* v, int n) {
        for (int i = 0; i < n; ++i) {
            *p++ = ',';
            p = detail::put_double(p, end, v[i]);
        }
        return p;
    }

    static void append_header_row(std::string& out, bool gt, bool world, bool keyframes) {
        out += "t_ns,state,imu_init,map_id,imu_ba2,n_extracted,n_inliers,n_frustum";
        for (int k = 0; k < kBins; ++k) {
            out += ",bin_";
            out += std::to_string(k);
        }
        out += ",vis_px,vis_py,vis_pz,vis_qw,vis_qx,vis_qy,vis_qz,vis_vx,vis_vy,vis_vz"
               ",imu_dt,imu_dpx,imu_dpy,imu_dpz,imu_dvx,imu_dvy,imu_dvz,imu_dqw,imu_dqx,imu_dqy,imu_dqz";
        if (gt) out += ",gt_px,gt_py,gt_pz,gt_qw,gt_qx,gt_qy,gt_qz";
        if (world) out += ",world_qw,world_qx,world_qy,world_qz,world_tx,world_ty,world_tz,world_s";
        if (keyframes) out += ",events,traj,ref_kf,rel_px,rel_py,rel_pz,rel_qw,rel_qx,rel_qy,rel_qz";
        out += '\n';
    }

    // Required keys and the types jsve's reader accepts for the keys it knows (schema.py).
    static bool check_metadata(const Metadata& meta, std::string& why) {
        using K = Metadata::Kind;
        if (!meta.error().empty()) {
            why = meta.error();
            return false;
        }
        struct Rule {
            const char* key;
            bool required;
            bool string, integer, number, array;
        };
        static const Rule rules[] = {
            {"sequence", true, true, false, false, false},  {"run", true, false, true, false, false},
            {"fps", true, false, true, true, false},        {"disturbance", false, true, false, false, false},
            {"level", false, false, true, true, false},     {"sensor", false, true, false, false, false},
            {"n_features", false, false, true, false, false}, {"image_size", false, false, false, false, true},
            {"grid", false, false, false, false, true},     {"gravity", false, false, false, false, true},
            {"frontend", false, true, false, false, false}, {"seed", false, false, true, false, false},
            {"gt_missing_frames", false, false, true, false, false}, {"gt_source", false, true, false, false, false},
            // A JSON object form of "rule" exists (jsve.core._rules.rule_to_dict); this header
            // writes the preset name.
            {"rule", false, true, false, false, false},     {"switch_model", false, true, false, false, false},
            {"camera_in_body", false, false, false, false, true},
        };
        for (const Rule& r : rules) {
            K k;
            if (!meta.kind(r.key, k)) {
                if (r.required) {
                    why = std::string("metadata lacks the required key \"") + r.key + "\"";
                    return false;
                }
                continue;
            }
            const bool ok = (r.string && k == K::kString) || (r.integer && k == K::kInt) ||
                            (r.number && k == K::kDouble) || (r.array && (k == K::kIntArray || k == K::kDoubleArray));
            if (!ok) {
                why = std::string("metadata \"") + r.key + "\" has the wrong type (expected " +
                      (r.string ? "a string" : r.array ? "an array" : r.number ? "a number" : "an integer") + ")";
                return false;
            }
        }
        // Value rules of jsve.io._logs (beyond types).
        std::vector<double> v;
        K k;
        meta.numbers("fps", v);
        if (!(v.size() == 1 && v[0] > 0.0)) {
            why = "metadata \"fps\" must be a positive number of frames per second";
            return false;
        }
        if (meta.numbers("gravity", v) && v.size() != 3) {
            why = "metadata \"gravity\" must be a list of 3 numbers (world gravity, m/s^2)";
            return false;
        }
        if (meta.numbers("image_size", v) && (!meta.kind("image_size", k) || k != K::kIntArray || v.size() != 2 ||
                                              !(v[0] > 0.0 && v[1] > 0.0))) {
            why = "metadata \"image_size\" must be [width, height]: two positive integers (pixels)";
            return false;
        }
        if (meta.numbers("grid", v) && !(v.size() == 2 && v[0] == 8.0 && v[1] == 8.0)) {
            why = "metadata \"grid\" must be [8, 8] (SVE bins, cols x rows)";
            return false;
        }
        if (meta.numbers("gt_missing_frames", v) && v[0] < 0.0) {
            why = "metadata \"gt_missing_frames\" must be >= 0";
            return false;
        }
        if (meta.numbers("camera_in_body", v) && !is_pose(v)) {
            why = "metadata \"camera_in_body\" must be the camera pose in the body frame, [qw, qx, qy, qz, tx, ty, tz] "
                  "(unit quaternion, m)";
            return false;
        }
        return true;
    }

    // [qw, qx, qy, qz, tx, ty, tz] within float32's range with a unit quaternion (jsve.io._logs._is_pose).
    static bool is_pose(const std::vector<double>& v) {
        if (v.size() != 7) return false;
        for (const double x : v)
            if (!(std::fabs(x) <= kFloatMax)) return false;
        const double norm = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3]);
        return std::fabs(norm - 1.0) <= kUnitQuaternionTolerance;
    }

    Status validate(const Frame& f, std::string& msg) const {
        if (have_last_ && f.t_ns <= last_t_ns_) {
            msg = "t_ns " + std::to_string(f.t_ns) + " is not after the previous frame's " + std::to_string(last_t_ns_);
            return Status::kNonIncreasingStamp;
        }
        if (f.state < -1 || f.state > 5) {
            msg = "state " + std::to_string(f.state) + " is not an ORB-SLAM3 tracking state (-1..5)";
            return Status::kOutOfRange;
        }
        if (f.map_id < 0) {
            msg = "map_id " + std::to_string(f.map_id) + " is negative (Map::GetId() is unsigned)";
            return Status::kOutOfRange;
        }
        if (f.imu_ba2 && !f.imu_init) {
            msg = "imu_ba2 is set but imu_init is not (inertial BA2 runs only on a map whose IMU is initialised)";
            return Status::kOutOfRange;
        }
        // OK 2, RECENTLY_LOST 3, OK_KLT 5: the front-end has a pose in these states.
        if (!f.has_pose && (f.state == 2 || f.state == 3 || f.state == 5)) {
            msg = "no pose (has_pose false) in state " + std::to_string(f.state) +
                  ": frames in states 2, 3, 5 (OK, RECENTLY_LOST, OK_KLT) have one";
            return Status::kOutOfRange;
        }
        if (f.n_extracted < 0 || f.n_inliers < 0 || f.n_frustum < 0) {
            msg = "negative count (n_extracted " + std::to_string(f.n_extracted) + ", n_inliers " +
                  std::to_string(f.n_inliers) + ", n_frustum " + std::to_string(f.n_frustum) + ")";
            return Status::kOutOfRange;
        }
        if (f.n_inliers > f.n_extracted) {
            msg = "n_inliers " + std::to_string(f.n_inliers) + " exceeds n_extracted " + std::to_string(f.n_extracted);
            return Status::kOutOfRange;
        }
        std::int64_t binned = 0;
        for (int k = 0; k < kBins; ++k) {
            if (f.bins[k] < 0 || f.bins[k] > kBinMax) {
                msg = "bin_" + std::to_string(k) + " = " + std::to_string(f.bins[k]) + " is outside 0.." +
                      std::to_string(kBinMax) + " (jsve holds bins as uint16)";
                return Status::kOutOfRange;
            }
            binned += f.bins[k];
        }
        if (binned > f.n_extracted) {
            msg = "the bins hold " + std::to_string(binned) + " keypoints, more than n_extracted " +
                  std::to_string(f.n_extracted);
            return Status::kOutOfRange;
        }
        struct Group {
            const char* name;
            const double* v;
            int n;
        };
        // What this frame writes: without a pose vis_* is not written, without ground truth gt_*.
        const bool gt = options_.ground_truth && f.has_gt;
        const bool world = options_.world_frame;
        const bool rel = options_.keyframes && f.ref_kf >= 0;
        Group groups[14] = {};
        int n_groups = 0;
        if (f.has_pose) {
            groups[n_groups++] = {"vis_p", f.vis_p, 3};
            groups[n_groups++] = {"vis_q", f.vis_q, 4};
            groups[n_groups++] = {"vis_v", f.vis_v, 3};
        }
        groups[n_groups++] = {"imu_dt", &f.imu_dt, 1};
        groups[n_groups++] = {"imu_dp", f.imu_dp, 3};
        groups[n_groups++] = {"imu_dv", f.imu_dv, 3};
        groups[n_groups++] = {"imu_dq", f.imu_dq, 4};
        if (gt) {
            groups[n_groups++] = {"gt_p", f.gt_p, 3};
            groups[n_groups++] = {"gt_q", f.gt_q, 4};
        }
        if (world) {
            groups[n_groups++] = {"world_q", f.world_q, 4};
            groups[n_groups++] = {"world_t", f.world_t, 3};
            groups[n_groups++] = {"world_s", &f.world_s, 1};
        }
        if (rel) {
            groups[n_groups++] = {"rel_p", f.rel_p, 3};
            groups[n_groups++] = {"rel_q", f.rel_q, 4};
        }
        for (int g = 0; g < n_groups; ++g) {
            for (int i = 0; i < groups[g].n; ++i) {
                if (!std::isfinite(groups[g].v[i])) {
                    msg = std::string(groups[g].name) + "[" + std::to_string(i) + "] is " + detail::double_text(groups[g].v[i]);
                    return Status::kNonFinite;
                }
                if (std::fabs(groups[g].v[i]) > kFloatMax) {
                    msg = std::string(groups[g].name) + "[" + std::to_string(i) + "] is " +
                          detail::double_text(groups[g].v[i]) + ", beyond float32's range (jsve computes in float32)";
                    return Status::kOutOfRange;
                }
            }
        }
        if (f.imu_dt < 0.0) {
            msg = "imu_dt " + detail::double_text(f.imu_dt) + " is negative";
            return Status::kOutOfRange;
        }
        if (frames_ == 0) {  // nothing to preintegrate from before the first frame
            bool zero = f.imu_dt == 0.0 && f.imu_dq[0] == 1.0 && f.imu_dq[1] == 0.0 && f.imu_dq[2] == 0.0 &&
                        f.imu_dq[3] == 0.0;
            for (int i = 0; i < 3; ++i) zero = zero && f.imu_dp[i] == 0.0 && f.imu_dv[i] == 0.0;
            if (!zero) {
                msg = "the first frame must have imu_dt, imu_dp and imu_dv 0 and imu_dq the identity (1, 0, 0, 0): "
                      "there is no previous frame to preintegrate from";
                return Status::kOutOfRange;
            }
        }
        Group quats[5] = {};
        int n_quats = 0;
        if (f.has_pose) quats[n_quats++] = {"vis_q", f.vis_q, 4};
        quats[n_quats++] = {"imu_dq", f.imu_dq, 4};
        if (gt) quats[n_quats++] = {"gt_q", f.gt_q, 4};
        if (world) quats[n_quats++] = {"world_q", f.world_q, 4};
        if (rel) quats[n_quats++] = {"rel_q", f.rel_q, 4};
        for (int g = 0; g < n_quats; ++g) {
            const double* q = quats[g].v;
            const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
            if (!(std::fabs(norm - 1.0) <= kUnitQuaternionTolerance)) {
                msg = std::string(quats[g].name) + " has norm " + detail::double_text(norm) + ", not 1 (wxyz unit quaternion)";
                return Status::kOutOfRange;
            }
        }
        if (world && !(f.world_s > 0.0)) {
            msg = "world_s " + detail::double_text(f.world_s) + " is not positive (the scale of a similarity)";
            return Status::kOutOfRange;
        }
        if (options_.keyframes) {
            if ((f.events & ~kEventMask) != 0) {
                msg = "events " + std::to_string(f.events) + " has bits outside the known events (mask " +
                      std::to_string(kEventMask) + ")";
                return Status::kOutOfRange;
            }
            if (f.ref_kf < -1) {
                msg = "ref_kf " + std::to_string(f.ref_kf) + " is below -1 (-1: no reference keyframe)";
                return Status::kOutOfRange;
            }
            if (f.traj && f.ref_kf < 0) {
                msg = "traj is 1 without a reference keyframe (ref_kf -1)";
                return Status::kOutOfRange;
            }
        }
        return Status::kOk;
    }

    Status fail(Status s, const std::string& message) { return fail(s, message, options_.on_error); }
    Status fail(Status s, const std::string& message, OnError policy) {
        error_ = message;
        if (policy == OnError::kThrow) throw LogError(s, message);
        return s;
    }

    Status io_failure(const std::string& what) {
        const std::string text = partial_ + ": " + what + ": " + errno_text();
        failed_ = Status::kIoError;
        abandon();
        return fail(Status::kIoError, text);
    }

    static std::string errno_text() { return std::strerror(errno); }

    void take(LogWriter& o) noexcept {
        file_ = o.file_;
        o.file_ = nullptr;
        buffer_ = std::move(o.buffer_);  // the FILE keeps using the same heap buffer
        options_ = o.options_;
        path_ = std::move(o.path_);
        partial_ = std::move(o.partial_);
        error_ = std::move(o.error_);
        failed_ = o.failed_;
        frames_ = o.frames_;
        trailers_ = o.trailers_;
        last_t_ns_ = o.last_t_ns_;
        have_last_ = o.have_last_;
    }

    std::FILE* file_ = nullptr;
    std::unique_ptr<char[]> buffer_;  // outlives file_: ~LogWriter() closes the file before members die
    Options options_;
    std::string path_, partial_, error_;
    Status failed_ = Status::kOk;
    std::int64_t frames_ = 0;
    std::int64_t trailers_ = 0;
    std::int64_t last_t_ns_ = 0;
    bool have_last_ = false;
};

}  // namespace jsve

#endif  // JSVE_LOG_HPP
