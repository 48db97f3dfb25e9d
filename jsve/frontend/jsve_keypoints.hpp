// jsve_keypoints.hpp: header-only C++17 writer of jsve's keypoint side files (format v1), and
// Algorithm 1 of Masked ORB-SLAM3: whether a keypoint lies on a dynamic object of an instance mask.
//
// Part of jsve (GPL-3.0-or-later). The side-file format is jsve/io/_keypoints.py's and Algorithm 1 is
// jsve.masks.dynamic_keypoints's; docs/masks.md describes both. Standard library only, like
// jsve_log.hpp, whose Metadata, Status, error policy and number formatting this header shares:
//
//     #include "jsve_keypoints.hpp"      // g++ -std=c++17 -I"$(jsve frontend-include)" ...
//
//     jsve::Metadata meta;
//     meta.set("sequence", "V101").set("run", 0).set("image_size", {752, 480});
//     jsve::KeypointWriter kp("logs/run_000.keypoints.csv", meta);   // writes ....csv.partial
//     for (...each frame, each keypoint...) kp.write(t_ns, x, y, ux, uy, octave, inlier);
//     kp.close();                                  // end marker, then rename to ....csv
//
//     const jsve::InstanceMask mask{pixels, width, height, stride};   // 16-bit obj_id per pixel
//     if (jsve::on_dynamic_object(mask, x, y)) ...                     // Algorithm 1
//
// The file (docs/masks.md, "Keypoint side files, format v1"):
//     # jsve-keypoints v1 {"sequence": "V101", "run": 0, "image_size": [752, 480]}
//     t_ns,x,y,ux,uy,octave,inlier
//     1403715274312143104,612.25,187.5,608.1238,185.04855,0,1
//     # jsve-keypoints end keypoints=1
// Rows are grouped by frame in time order. Floats are written so that they read back, rounded to
// float, to the same bits (ORB-SLAM3 holds keypoints as floats); integers in full. As with the log,
// lines go to `<path>.partial` and close() alone writes the end marker and renames the file; a
// rejected row (a NaN or infinite coordinate, a negative octave, a stamp before the previous row's)
// is not written and fails the writer. Not thread-safe: one writer per run, from one thread.

#ifndef JSVE_KEYPOINTS_HPP
#define JSVE_KEYPOINTS_HPP

#include <cerrno>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <initializer_list>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "jsve_log.hpp"

namespace jsve {

// ---------------------------------------------------------------------------------------------
// Algorithm 1

inline constexpr int kClassCar = 1;         // KITTI MOTS class ids: obj_id = class_id * 1000 + instance
inline constexpr int kClassPedestrian = 2;  // (jsve.masks.DYNAMIC_CLASSES; 0 background, 10 ignore)

// Whether a pixel of an instance map (obj_id) belongs to a car or a pedestrian.
constexpr bool dynamic_object(std::uint16_t obj_id) noexcept {
    return obj_id / 1000 == kClassCar || obj_id / 1000 == kClassPedestrian;
}

// A view of a 16-bit instance map (pixel = obj_id), row-major: pixel (col, row) is
// pixels[row * stride + col]. Held by the caller; an empty view (pixels null) masks nothing.
struct InstanceMask {
    const std::uint16_t* pixels = nullptr;
    int width = 0, height = 0;
    std::ptrdiff_t stride = 0;  // elements from one row to the next (>= width)

    bool empty() const noexcept { return pixels == nullptr; }
    // Whether pixel (col, row) is on a dynamic object; a pixel outside the image is not.
    bool dynamic_at(long col, long row) const noexcept {
        if (col < 0 || row < 0 || col >= width || row >= height) return false;
        return dynamic_object(pixels[row * stride + col]);
    }
};

// Algorithm 1 (Masked ORB-SLAM3): a keypoint at (x, y) (x the column, y the row, px, as extracted) is
// on a dynamic object when the mask is set at any of (floor x, floor y), (floor x + 1, floor y),
// (floor x, floor y + 1), (floor x + 1, floor y + 1); a neighbour outside the image counts as not set
// (nothing wraps around or is clamped onto the border). jsve.masks.dynamic_keypoints, one keypoint.
inline bool on_dynamic_object(const InstanceMask& mask, double x, double y) noexcept {
    if (mask.empty()) return false;
    const double fx = std::floor(x), fy = std::floor(y);
    // All four neighbours lie outside beyond these bounds (and a NaN fails them): no cast overflows.
    if (!(fx >= -2.0 && fx <= mask.width && fy >= -2.0 && fy <= mask.height)) return false;
    const long c = static_cast<long>(fx), r = static_cast<long>(fy);
    return mask.dynamic_at(c, r) || mask.dynamic_at(c + 1, r) || mask.dynamic_at(c, r + 1) ||
           mask.dynamic_at(c + 1, r + 1);
}

// A coordinate in an image resized from `source` to `resized` pixels along this axis (as ORB-SLAM3
// resizes its input to Camera.newWidth x Camera.newHeight), in the source image's pixels: cv::resize's
// geometry, pixel centres at integers, (x + 0.5) * source / resized - 0.5, rounded to float as
// ORB-SLAM3 holds keypoints. x itself when the sizes agree. Masks describe the source image: Algorithm 1
// and the side file's x, y use this coordinate.
inline float source_coordinate(float x, int source, int resized) noexcept {
    if (source == resized || resized <= 0) return x;
    const double scale = static_cast<double>(source) / static_cast<double>(resized);
    return static_cast<float>((static_cast<double>(x) + 0.5) * scale - 0.5);
}

// ---------------------------------------------------------------------------------------------
// Keypoint side files

inline constexpr const char* kKeypointsMagic = "# jsve-keypoints v1 ";
inline constexpr const char* kKeypointsEndMarker = "# jsve-keypoints end keypoints=";
inline constexpr const char* kKeypointsHeader = "t_ns,x,y,ux,uy,octave,inlier\n";

// A log `runs/r7.csv` keeps its keypoints in `runs/r7.keypoints.csv` (jsve.io.keypoints_path).
inline std::string keypoints_path(const std::string& log_path) {
    const std::string csv = ".csv";
    const bool has_csv = log_path.size() >= csv.size() &&
                         log_path.compare(log_path.size() - csv.size(), csv.size(), csv) == 0;
    return (has_csv ? log_path.substr(0, log_path.size() - csv.size()) : log_path) + ".keypoints.csv";
}

struct KeypointOptions {
    bool overwrite = false;  // replace an existing `<path>` (removed at open)
    OnError on_error = OnError::kThrow;
};

class KeypointWriter {
public:
    KeypointWriter() = default;
    // Opens at once; see open().
    KeypointWriter(const std::string& path, const Metadata& meta, const KeypointOptions& options = {}) {
        open(path, meta, options);
    }
    ~KeypointWriter() { abandon(); }
    KeypointWriter(const KeypointWriter&) = delete;
    KeypointWriter& operator=(const KeypointWriter&) = delete;

    // Checks the metadata (jsve.io._keypoints: `sequence` a string, `run` an integer, `image_size`
    // [width, height] positive integers; `image_bounds`, when set, [min_x, max_x, min_y, max_y] with
    // min < max), creates `<path>.partial`, writes line 1 and the header row, and flushes them.
    // `<path>` itself must not exist unless options.overwrite, which removes it now.
    Status open(const std::string& path, const Metadata& meta, const KeypointOptions& options = {}) {
        if (file_ != nullptr) return fail(Status::kAlreadyOpen, "open(\"" + path + "\"): already writing " + partial_);
        options_ = options;
        failed_ = Status::kOk;
        error_.clear();
        rows_ = 0;
        last_t_ns_ = std::numeric_limits<std::int64_t>::min();
        path_ = path;
        partial_ = path + kPartialSuffix;
        if (path.empty()) return fail(Status::kIoError, "open(): empty path");
        std::string why;
        if (!check_metadata(meta, why)) return fail(Status::kBadMetadata, path + ": " + why);
        if (std::FILE* existing = std::fopen(path.c_str(), "rb")) {
            std::fclose(existing);
            if (!options_.overwrite) return fail(Status::kExists, path + ": exists (set overwrite to replace it)");
            if (std::remove(path.c_str()) != 0)
                return fail(Status::kIoError, path + ": cannot remove: " + std::strerror(errno));
        }
        file_ = std::fopen(partial_.c_str(), "wb");
        if (file_ == nullptr) return io_failure("cannot create");
        if (!buffer_) buffer_.reset(new char[kBufferSize]);
        std::setvbuf(file_, buffer_.get(), _IOFBF, kBufferSize);
        const std::string head = kKeypointsMagic + meta.to_json() + "\n" + kKeypointsHeader;
        if (std::fwrite(head.data(), 1, head.size(), file_) != head.size() || std::fflush(file_) != 0)
            return io_failure("cannot write the header");
        return Status::kOk;
    }

    // Appends one keypoint of the frame stamped `t_ns` (ns; frames in time order): its position in the
    // image the masks describe (x, y, px: as extracted, or source_coordinate when the front-end resized
    // the image), undistorted where the front-end grids it (ux, uy, px), its pyramid level and whether
    // it is a tracking inlier.
    Status write(std::int64_t t_ns, float x, float y, float ux, float uy, int octave, bool inlier) {
        if (file_ == nullptr) return fail(Status::kNotOpen, "write(): the writer is not open");
        if (failed_ != Status::kOk) return fail(Status::kFailed, partial_ + ": writer failed earlier: " + error_);
        const char* bad = nullptr;
        Status s = Status::kOk;
        if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(ux) || !std::isfinite(uy))
            bad = "a coordinate is NaN or infinite", s = Status::kNonFinite;
        else if (octave < 0) bad = "octave is negative", s = Status::kOutOfRange;
        else if (t_ns < last_t_ns_) bad = "t_ns is before the previous row's", s = Status::kNonIncreasingStamp;
        if (bad != nullptr) {
            failed_ = s;
            return fail(s, partial_ + ": keypoint " + std::to_string(rows_) + " rejected: " + bad);
        }
        char line[kLineCapacity];
        char* const end = line + sizeof line;
        char* p = detail::put_int(line, end, t_ns);
        for (const float v : {x, y, ux, uy}) {
            *p++ = ',';
            p = detail::put_float(p, end, v);
        }
        *p++ = ',';
        p = detail::put_int(p, end, octave);
        *p++ = ',';
        *p++ = inlier ? '1' : '0';
        *p++ = '\n';
        const auto n = static_cast<std::size_t>(p - line);
        if (std::fwrite(line, 1, n, file_) != n) return io_failure("cannot write keypoint " + std::to_string(rows_));
        ++rows_;
        last_t_ns_ = t_ns;
        return Status::kOk;
    }

    // Hands what the stdio buffer holds to the operating system.
    Status flush() {
        if (file_ == nullptr) return fail(Status::kNotOpen, "flush(): the writer is not open");
        if (std::fflush(file_) != 0) return io_failure("cannot flush");
        return Status::kOk;
    }

    // Writes the end marker, closes and renames `<path>.partial` to `<path>` (a file of no rows is
    // complete: a run whose frames had no keypoints). A failed writer keeps `.partial` (kFailed).
    Status close() {
        if (file_ == nullptr) return fail(Status::kNotOpen, "close(): the writer is not open");
        if (failed_ != Status::kOk) {
            abandon();
            return fail(Status::kFailed, partial_ + ": not finalised, the writer failed earlier: " + error_);
        }
        const std::string tail = kKeypointsEndMarker + std::to_string(rows_) + "\n";
        if (std::fwrite(tail.data(), 1, tail.size(), file_) != tail.size() || std::fflush(file_) != 0)
            return io_failure("cannot write the end marker");
        std::FILE* f = file_;
        file_ = nullptr;
        if (std::fclose(f) != 0) return io_failure("close failed");
#ifdef _WIN32
        std::remove(path_.c_str());  // rename does not replace an existing file on Windows
#endif
        if (std::rename(partial_.c_str(), path_.c_str()) != 0) return io_failure("cannot rename to " + path_);
        return Status::kOk;
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
    std::int64_t rows() const noexcept { return rows_; }
    const std::string& last_error() const noexcept { return error_; }
    const std::string& path() const noexcept { return path_; }
    const std::string& partial_path() const noexcept { return partial_; }

private:
    static constexpr std::size_t kBufferSize = std::size_t{1} << 16;  // stdio buffer, 64 KiB
    static constexpr std::size_t kLineCapacity = 21 + 4 * 19 + 12 + 4;  // t_ns, 4 floats, octave, inlier

    static bool check_metadata(const Metadata& meta, std::string& why) {
        if (!meta.error().empty()) return why = meta.error(), false;
        Metadata::Kind kind;
        std::vector<double> v;
        if (!meta.kind("sequence", kind) || kind != Metadata::Kind::kString)
            return why = "metadata \"sequence\" must be a string (required)", false;
        if (!meta.kind("run", kind) || kind != Metadata::Kind::kInt)
            return why = "metadata \"run\" must be an integer (required)", false;
        if (!meta.kind("image_size", kind) || kind != Metadata::Kind::kIntArray || !meta.numbers("image_size", v) ||
            v.size() != 2 || !(v[0] > 0 && v[1] > 0))
            return why = "metadata \"image_size\" must be [width, height], positive integers (required)", false;
        if (meta.kind("image_bounds", kind) &&
            ((kind != Metadata::Kind::kIntArray && kind != Metadata::Kind::kDoubleArray) ||
             !meta.numbers("image_bounds", v) || v.size() != 4 || !(v[0] < v[1] && v[2] < v[3])))
            return why = "metadata \"image_bounds\" must be [min_x, max_x, min_y, max_y] with min < max", false;
        return true;
    }

    Status fail(Status s, const std::string& message) {
        error_ = message;
        if (options_.on_error == OnError::kThrow) throw LogError(s, message);
        return s;
    }

    Status io_failure(const std::string& what) {
        const std::string text = partial_ + ": " + what + ": " + std::strerror(errno);
        failed_ = Status::kIoError;
        abandon();
        return fail(Status::kIoError, text);
    }

    std::FILE* file_ = nullptr;
    std::unique_ptr<char[]> buffer_;  // outlives file_: ~KeypointWriter() closes the file first
    KeypointOptions options_;
    std::string path_, partial_, error_;
    Status failed_ = Status::kOk;
    std::int64_t rows_ = 0;
    std::int64_t last_t_ns_ = std::numeric_limits<std::int64_t>::min();
};

}  // namespace jsve

#endif  // JSVE_KEYPOINTS_HPP
