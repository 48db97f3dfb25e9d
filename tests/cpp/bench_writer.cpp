// Times jsve_log.hpp: N frames of realistic values written to a real file, repeated; prints one
// JSON object. Driven by benchmarks/bench_frontend_writer.py, which compiles it with -O2.
//
// usage: bench_writer OUT.csv N_FRAMES REPEATS

#include "jsve_log.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

namespace {

std::uint64_t g_state = 12345;

double uniform() {  // splitmix64 -> [0, 1)
    std::uint64_t z = (g_state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return static_cast<double>((z ^ (z >> 31)) >> 11) * 0x1.0p-53;
}

void unit_quaternion(double q[4]) {
    double n = 0.0;
    for (int i = 0; i < 4; ++i) {
        q[i] = uniform() - 0.5;
        n += q[i] * q[i];
    }
    n = std::sqrt(n);
    for (int i = 0; i < 4; ++i) q[i] /= n;
}

// A frame as ORB-SLAM3 on EuRoC would log it: ~1000 keypoints, metres, m/s, 50 ms of IMU.
jsve::Frame realistic(std::int64_t i) {
    jsve::Frame f;
    f.t_ns = 1403636579763555584 + i * 50000000;
    f.state = 2;
    f.imu_init = true;
    f.imu_ba2 = i >= 300;  // inertial BA2 once the map is 15 s old (20 fps)
    int binned = 0;
    for (int k = 0; k < jsve::kBins; ++k) binned += (f.bins[k] = static_cast<int>(uniform() * 30.0));
    f.n_extracted = binned + 20;
    f.n_inliers = static_cast<int>(uniform() * 300.0);
    f.n_frustum = f.n_inliers + static_cast<int>(uniform() * 200.0);
    for (double& v : f.vis_p) v = 10.0 * (uniform() - 0.5);
    unit_quaternion(f.vis_q);
    for (double& v : f.vis_v) v = uniform() - 0.5;
    if (i > 0) {  // the first frame has no preintegration
        f.imu_dt = 0.05;
        for (double& v : f.imu_dp) v = 0.05 * (uniform() - 0.5);
        for (double& v : f.imu_dv) v = 0.5 * (uniform() - 0.5);
        unit_quaternion(f.imu_dq);
    }
    return f;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 4) {
        std::fprintf(stderr, "usage: %s OUT.csv N_FRAMES REPEATS\n", argv[0]);
        return 2;
    }
    const std::string out = argv[1];
    const long n = std::strtol(argv[2], nullptr, 10);
    const int repeats = std::atoi(argv[3]);
    std::vector<jsve::Frame> frames;
    frames.reserve(static_cast<std::size_t>(n));
    for (long i = 0; i < n; ++i) frames.push_back(realistic(i));

    jsve::Metadata meta;
    meta.set("sequence", "bench").set("run", 0).set("fps", 20);
    jsve::Options options;
    options.overwrite = true;
    std::vector<double> us_per_frame;
    long bytes = 0;
    for (int r = 0; r < repeats; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
        jsve::LogWriter log(out, meta, options);
        for (const jsve::Frame& f : frames) log.write(f);
        log.close();
        const auto t1 = std::chrono::steady_clock::now();
        us_per_frame.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count() / static_cast<double>(n));
        if (std::FILE* f = std::fopen(out.c_str(), "rb")) {
            std::fseek(f, 0, SEEK_END);
            bytes = std::ftell(f);
            std::fclose(f);
        }
    }
    // The hook's other per-frame work: binning ORB-SLAM3's 64 x 48 grid of keypoint indices.
    static std::vector<std::size_t> grid[jsve::kGridCols][jsve::kGridRows];
    for (std::size_t i = 0; i < 1000; ++i)
        grid[static_cast<int>(uniform() * jsve::kGridCols)][static_cast<int>(uniform() * jsve::kGridRows)].push_back(i);
    jsve::Frame scratch;
    long checksum = 0;
    const auto b0 = std::chrono::steady_clock::now();
    for (long i = 0; i < n; ++i) {
        jsve::fill_bins_from_grid(scratch, [&](int c, int r) { return grid[c][r].size(); });
        checksum += scratch.bins[i % jsve::kBins];
    }
    const auto b1 = std::chrono::steady_clock::now();
    const double bins_us = std::chrono::duration<double, std::micro>(b1 - b0).count() / static_cast<double>(n);

    std::vector<double> sorted = us_per_frame;
    std::sort(sorted.begin(), sorted.end());
    std::printf("{\"frames\": %ld, \"repeats\": %d, \"fp_to_chars\": %s, \"bytes_per_frame\": %.1f, "
                "\"bins_us_per_frame\": %.4f, \"bins_checksum\": %ld, "
                "\"median_us_per_frame\": %.4f, \"min_us_per_frame\": %.4f, \"us_per_frame\": [",
                n, repeats, JSVE_LOG_HAVE_FP_TO_CHARS ? "true" : "false", static_cast<double>(bytes) / static_cast<double>(n),
                bins_us, checksum, sorted[sorted.size() / 2], sorted.front());
    for (std::size_t i = 0; i < us_per_frame.size(); ++i) std::printf("%s%.4f", i ? ", " : "", us_per_frame[i]);
    std::printf("]}\n");
    return 0;
}
