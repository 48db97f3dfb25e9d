// Writes a format-v2 log of a deterministic synthetic run with jsve_log.hpp, and a sidecar file
// holding every value it wrote (integers in decimal, doubles as the hex of their bits), so that
// tests/test_frontend.py can check the reader bit for bit. Used only by the tests.
//
// usage: write_synthetic OUT.csv N_FRAMES [--gt] [--world] [--flush N] [--expected PATH]
//                        [--locale NAME] [--kill-after K] [--no-close]
//   --world         the eight world_* columns (Options::world_frame): the identity on frames 0..9,
//                   then a similarity that changes every 7 frames (random rotation and translation,
//                   positive scales including subnormal and float32's largest), on every frame.
//   --kill-after K  after K frames (flushed when --flush 1), print "READY" on stdout and sleep
//                   until killed; the test sends SIGKILL.
//   --no-close      return from main without close(): the destructor abandons the log.

#include "jsve_log.hpp"

#include <chrono>
#include <cinttypes>
#include <clocale>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <string>
#include <thread>

namespace {

std::uint64_t g_state = 0x9E3779B97F4A7C15ull;

// splitmix64: deterministic bits, identical on every platform.
std::uint64_t next_bits() {
    std::uint64_t z = (g_state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

double from_bits(std::uint64_t b) {
    double d;
    std::memcpy(&d, &b, sizeof d);
    return d;
}

std::uint64_t to_bits(double d) {
    std::uint64_t b;
    std::memcpy(&b, &d, sizeof b);
    return b;
}

// Any double the reader accepts, subnormals and signed zeros included: random bits with an exponent
// within float32's range (|x| <= FLT_MAX; the reader refuses larger values, jsve computes in float32).
double random_finite() {
    for (;;) {
        std::uint64_t b = next_bits();
        if (((b >> 52) & 0x7FF) == 0x7FF) b &= ~(std::uint64_t{1} << 62);
        const double d = from_bits(b);
        if (std::fabs(d) <= 3.4028234663852886e38) return d;
    }
}

double unit_interval() { return static_cast<double>(next_bits() >> 11) * 0x1.0p-53; }

void random_unit_quaternion(double q[4]) {
    double n = 0.0;
    do {
        for (int i = 0; i < 4; ++i) q[i] = 2.0 * unit_interval() - 1.0;
        n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    } while (n < 0.1);
    for (int i = 0; i < 4; ++i) q[i] /= n;
}

const double kSpecial[] = {
    0.1,
    1e-300,
    -0.0,
    0.0,
    5e-324,                       // smallest subnormal
    -2.5e-310,                    // subnormal
    3.4028234663852886e38,        // float32's largest, the reader's bound (a double beyond is refused)
    -3.4028234663852886e38,
    std::numeric_limits<double>::min(),
    9007199254740993.0,           // 2^53 + 1 rounds to 2^53
    1.0 / 3.0,
    1e22,
    1e23,
    0.30000000000000004,
    123456789.123456789,
    -1.0,
    1.0,
};
constexpr int kNumSpecial = sizeof kSpecial / sizeof kSpecial[0];

void put_hex(std::FILE* f, const double* v, int n) {
    for (int i = 0; i < n; ++i) std::fprintf(f, " %016" PRIx64, to_bits(v[i]));
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 3) {
        std::fprintf(stderr, "usage: %s OUT.csv N_FRAMES [options]\n", argv[0]);
        return 2;
    }
    const std::string out = argv[1];
    const long n_frames = std::strtol(argv[2], nullptr, 10);
    bool gt = false, world = false, close_log = true;
    int flush_every = 100;
    long kill_after = -1;
    std::string expected_path, locale_name;
    for (int a = 3; a < argc; ++a) {
        const std::string opt = argv[a];
        if (opt == "--gt") gt = true;
        else if (opt == "--world") world = true;
        else if (opt == "--no-close") close_log = false;
        else if (opt == "--flush" && a + 1 < argc) flush_every = std::atoi(argv[++a]);
        else if (opt == "--kill-after" && a + 1 < argc) kill_after = std::strtol(argv[++a], nullptr, 10);
        else if (opt == "--expected" && a + 1 < argc) expected_path = argv[++a];
        else if (opt == "--locale" && a + 1 < argc) locale_name = argv[++a];
        else {
            std::fprintf(stderr, "unknown option %s\n", opt.c_str());
            return 2;
        }
    }
    if (!locale_name.empty() && std::setlocale(LC_ALL, locale_name.c_str()) == nullptr) {
        std::fprintf(stderr, "locale %s not available\n", locale_name.c_str());
        return 3;
    }
    std::fprintf(stderr, "decimal_point=%s\n", std::localeconv()->decimal_point);  // the test checks it took effect

    jsve::Metadata meta;
    meta.set("sequence", "placeholder")
        .set("run", 99)
        .set("fps", 20)
        .set("disturbance", "blur")
        .set("level", 2.5)
        .set("sensor", "imu_monocular")
        .set("n_features", 1000)
        .set("image_size", {752, 480})
        .set("grid", {8, 8})
        .set("gravity", {0.0, 0.0, -9.81})
        .set("frontend", "jsve write_synthetic (test)")
        .set("seed", (std::int64_t{1} << 40) + 3)
        .set("rule", "sve-option2")
        .set("switch_model", "orbslam3")
        .set("neg_zero", -0.0)
        .set("tiny", 5e-324)
        .set("big", std::numeric_limits<std::int64_t>::max())
        .set("most_negative", std::numeric_limits<std::int64_t>::min())
        .set("awkward", {0.1, 1e-300, -0.0, std::numeric_limits<double>::max()});
    // Replacing values keeps each key where it was first set.
    meta.set("sequence", "MH_04 \"quoted\" \\ back\nline\ttab \xC3\xBC \xE6\xBC\xA2\xE5\xAD\x97 \x01\x7F/end").set("run", 7);

    jsve::Options options;
    options.ground_truth = gt;
    options.world_frame = world;
    options.flush_every = flush_every;
    options.overwrite = true;
    jsve::LogWriter log(out, meta, options);

    std::FILE* expected = nullptr;
    if (!expected_path.empty()) {
        expected = std::fopen(expected_path.c_str(), "w");
        if (expected == nullptr) return 4;
    }

    const std::int64_t two53 = std::int64_t{1} << 53;
    for (long i = 0; i < n_frames; ++i) {
        jsve::Frame f;
        if (i < 2) f.t_ns = two53 + 1 + i;  // not representable as a double
        else f.t_ns = 1403636579763555584 + (i - 2) * 50000000 + (i % 7);
        f.state = static_cast<int>(i % 7) - 1;
        f.imu_init = (i % 3 == 0);
        f.map_id = i < 20 ? 0 : (i < 40 ? 3 : (std::int64_t{1} << 40));  // a new map, then an id past int32
        f.imu_ba2 = f.imu_init && i >= 30;
        const bool posed_state = f.state == 2 || f.state == 3 || f.state == 5;
        f.has_pose = posed_state || i % 2 == 1;  // even frames outside states 2, 3, 5 have no pose

        static int grid[jsve::kGridCols][jsve::kGridRows];
        for (int c = 0; c < jsve::kGridCols; ++c)
            for (int r = 0; r < jsve::kGridRows; ++r) grid[c][r] = static_cast<int>(next_bits() % 4 == 0 ? next_bits() % 5 : 0);
        jsve::fill_bins_from_grid(f, [&](int c, int r) { return grid[c][r]; });
        int binned = 0;
        for (int k = 0; k < jsve::kBins; ++k) binned += f.bins[k];
        f.n_extracted = binned + static_cast<int>(next_bits() % 50);
        f.n_inliers = static_cast<int>(next_bits() % static_cast<std::uint64_t>(f.n_extracted + 1));
        f.n_frustum = static_cast<int>(next_bits() % 2000);

        f.vis_p[0] = kSpecial[i % kNumSpecial];
        f.vis_p[1] = random_finite();
        f.vis_p[2] = kSpecial[(i * 5 + 3) % kNumSpecial];
        random_unit_quaternion(f.vis_q);
        for (double& v : f.vis_v) v = random_finite();
        if (!f.has_pose) f.vis_p[1] = std::numeric_limits<double>::quiet_NaN();  // not written, not checked
        f.imu_dt = (i == 0) ? 0.0 : (i % 4 == 1 ? std::fabs(random_finite()) : 0.05 + 1e-3 * unit_interval());
        if (i > 0) {  // the first frame has nothing to preintegrate from: zeros and identity
            for (double& v : f.imu_dp) v = random_finite();
            f.imu_dv[0] = kSpecial[(i * 3 + 1) % kNumSpecial];
            f.imu_dv[1] = random_finite();
            f.imu_dv[2] = unit_interval();
            random_unit_quaternion(f.imu_dq);
        }
        if (gt) {
            f.has_gt = (i % 5 != 3);  // some frames without ground truth: empty gt_* fields
            for (double& v : f.gt_p) v = random_finite();
            random_unit_quaternion(f.gt_q);
        }
        static jsve::Frame w;  // the world frame: the identity, then one per 7 frames from frame 10
        if (world && i >= 10 && (i - 10) % 7 == 0) {
            random_unit_quaternion(w.world_q);
            for (double& v : w.world_t) v = random_finite();
            const double scales[] = {5e-324, 3.4028234663852886e38, 1.0 / 3.0, 0.1};
            const long k = (i - 10) / 7;
            w.world_s = k < 4 ? scales[k] : std::fabs(random_finite());
            if (!(w.world_s > 0.0)) w.world_s = 2.0;
        }
        if (world) {
            for (int k = 0; k < 4; ++k) f.world_q[k] = w.world_q[k];
            for (int k = 0; k < 3; ++k) f.world_t[k] = w.world_t[k];
            f.world_s = w.world_s;
        } else {
            f.world_s = 0.0;  // not written without world_frame, so not checked
        }

        log.write(f);

        if (expected != nullptr) {
            std::fprintf(expected, "F %" PRId64 " %d %d %" PRId64 " %d %d %d %d", f.t_ns, f.state, f.imu_init ? 1 : 0,
                         f.map_id, f.imu_ba2 ? 1 : 0, f.n_extracted, f.n_inliers, f.n_frustum);
            for (int k = 0; k < jsve::kBins; ++k) std::fprintf(expected, " %d", f.bins[k]);
            if (f.has_pose) {
                put_hex(expected, f.vis_p, 3);
                put_hex(expected, f.vis_q, 4);
                put_hex(expected, f.vis_v, 3);
            } else {
                std::fprintf(expected, " - - - - - - - - - -");  // no pose: NaN when read
            }
            put_hex(expected, &f.imu_dt, 1);
            put_hex(expected, f.imu_dp, 3);
            put_hex(expected, f.imu_dv, 3);
            put_hex(expected, f.imu_dq, 4);
            if (gt && f.has_gt) {
                put_hex(expected, f.gt_p, 3);
                put_hex(expected, f.gt_q, 4);
            } else if (gt) {
                std::fprintf(expected, " - - - - - - -");  // no ground truth: NaN when read
            }
            if (world) {
                put_hex(expected, f.world_q, 4);
                put_hex(expected, f.world_t, 3);
                put_hex(expected, &f.world_s, 1);
            }
            std::fprintf(expected, "\n");
            if (i < 3) {  // the raw grid, so the test can bin it independently
                std::fprintf(expected, "G %ld", i);
                for (int c = 0; c < jsve::kGridCols; ++c)
                    for (int r = 0; r < jsve::kGridRows; ++r) std::fprintf(expected, " %d", grid[c][r]);
                std::fprintf(expected, "\n");
            }
        }

        if (kill_after >= 0 && i + 1 == kill_after) {
            if (expected != nullptr) std::fclose(expected);
            std::printf("READY\n");
            std::fflush(stdout);
            for (;;) std::this_thread::sleep_for(std::chrono::seconds(1));
        }
    }
    if (expected != nullptr) std::fclose(expected);
    if (close_log) log.close();
    return 0;
}
