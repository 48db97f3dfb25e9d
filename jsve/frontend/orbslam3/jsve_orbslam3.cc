// jsve_orbslam3: runs ORB-SLAM3 v1.0 (IMU_MONOCULAR or MONOCULAR) over one EuRoC-format sequence and
// writes a jsve tracking log through the hook (jsve_orbslam3_hook.hpp), plus ORB-SLAM3's own trajectory.
//
//   jsve_orbslam3 --vocabulary VOC.txt --settings EuRoC.yaml --sequence DIR --log OUT.csv
//                 [--trajectory OUT.txt] [--summary OUT.json] [--meta KEY=VALUE]... [--overwrite]
//                 [--sensor imu-monocular|monocular]   (default imu-monocular; monocular tracks the
//                               images alone, with ORB-SLAM3's own success test: no --rule-*)
//                 [--masks]     (DIR/mav0/cam0/masks/<image name>.png, one 16-bit instance map per image,
//                               pixel = obj_id = class * 1000 + instance: keypoints on cars (1) and
//                               pedestrians (2) are dropped in ORB-SLAM3's Frame, Algorithm 1; the log's
//                               `masks` trailer has the counts per frame)
//                 [--keypoints] (every frame's keypoints in OUT.keypoints.csv, jsve's side file v1)
//                 [--no-wait]   (default: frames paced at the camera's rate, as ORB-SLAM3's examples do)
//                 [--lockstep [--gate-timeout SECONDS]]   (threads take turns: a run depends only on its
//                               inputs and seed; never paced; jsve_orbslam3_lockstep.hpp)
//                 [--seed S]    (seeds the process's rand() stream, which every RANSAC of ORB-SLAM3
//                               draws from, with S + 1; default and S = 0: ORB-SLAM3's own draws)
//                 [--branch-at K --branch-frames W --branch-log OUT.csv [--branch-summary OUT.json]
//                  [--branch-rule-inliers ...|--branch-rule-sve ... [--branch-coast]]]   (with --lockstep:
//                               before frame K, fork; the child goes on for W frames under the branch's
//                               rule, default the run's own, writing its own log (a path as long as
//                               --log's), which holds every row before K too; the parent waits for it,
//                               then goes on)
//                 [--rule-inliers IMU_INIT,NOT_INIT,RELOC,RECOVERY [--coast]]   (default: ORB-SLAM3's test)
//                 [--rule-sve INPUTS,W_A,U_B,P,Q,RHO,IMU_INIT,NOT_INIT,RELOC,RECOVERY [--coast]]
//                 [--n-features N]   (ORBextractor.nFeatures, S_a of the authors' Eq.1; default 1000)
// INPUTS of an SVE rule: jsve, authors-eq1 or authors-option1 (jsve.core._sve.INPUTS; the authors'
// inputs need P = Q = 1).
//
// DIR holds mav0/cam0/data.csv (`t_ns,file`), mav0/cam0/data/<file> and (IMU_MONOCULAR) mav0/imu0/data.csv
// (`t_ns,wx,wy,wz,ax,ay,az`, EuRoC's column order). --meta values are typed like JSON scalars and lists:
// `run=3` an integer, `fps=20.0` a float, `image_size=[752,480]` a list, `key="..."` a string (so a
// hash of digits stays one), anything else a string too.
// Exit status: 0 on success, 1 when the run or its log failed (the log then stays `.partial`), 2 on
// bad arguments or input (a mask missing, unreadable or not a 16-bit map of the image's size), 3 when a lockstep gate did not open within --gate-timeout (the summary says
// so). The driver dies with the process that started it (a killed `jsve frontend run` leaves no run
// behind). It is jsve's own program, not one of ORB-SLAM3's examples.
#include <malloc.h>
#include <pthread.h>
#include <signal.h>
#include <sys/personality.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgcodecs.hpp>

#include <opencv2/core.hpp>

#include "ImuTypes.h"
#include "System.h"
#include "Thirdparty/DBoW2/DUtils/Random.h"
#include "jsve_orbslam3_hook.hpp"

namespace {

struct Args {
    std::string vocabulary, settings, sequence, log, trajectory, summary;
    std::vector<std::pair<std::string, std::string>> meta;
    bool overwrite = false;
    bool wait = true;  // pace frames at the camera's rate, as a live camera (and ORB-SLAM3's examples) do
    bool has_rule = false, coast = false;
    jsve_hook::Rule rule;
    bool lockstep = false;
    double gate_timeout_s = 60.0;
    bool has_seed = false;
    long long seed = 0;
    long long branch_at = -1, branch_frames = 0;
    std::string branch_log, branch_summary;
    bool branch_has_rule = false, branch_coast = false;
    jsve_hook::Rule branch_rule;
    bool imu = true;  // --sensor: IMU_MONOCULAR (true) or MONOCULAR
    bool masks = false, keypoints = false;
};

// Where --masks finds an image's mask, relative to the dataset (the log's `masks` metadata says so).
const char* const kMaskFolder = "mav0/cam0/masks";

// A mask that is missing or unusable: bad input (exit 2), named by its file.
struct BadInput : std::runtime_error {
    using std::runtime_error::runtime_error;
};

[[noreturn]] void usage_error(const std::string& message) {
    std::cerr << "jsve_orbslam3: " << message << "\n";
    std::exit(2);
}

bool parse_int(const std::string& s, long long* out) {
    if (s.empty()) return false;
    char* end = nullptr;
    *out = std::strtoll(s.c_str(), &end, 10);
    return *end == '\0';
}

bool parse_double(const std::string& s, double* out) {
    if (s.empty()) return false;
    std::istringstream in(s);
    in.imbue(std::locale::classic());
    in >> *out;
    return in && in.peek() == EOF;
}

Args parse_args(int argc, char** argv) {
    Args a;
    for (int i = 1; i < argc; ++i) {
        const std::string key = argv[i];
        auto value = [&]() -> std::string {
            if (i + 1 >= argc) usage_error(key + " needs a value");
            return argv[++i];
        };
        if (key == "--vocabulary") a.vocabulary = value();
        else if (key == "--settings") a.settings = value();
        else if (key == "--sequence") a.sequence = value();
        else if (key == "--log") a.log = value();
        else if (key == "--trajectory") a.trajectory = value();
        else if (key == "--summary") a.summary = value();
        else if (key == "--overwrite") a.overwrite = true;
        else if (key == "--no-wait") a.wait = false;
        else if (key == "--coast") a.coast = true;
        else if (key == "--lockstep") a.lockstep = true;
        else if (key == "--masks") a.masks = true;
        else if (key == "--keypoints") a.keypoints = true;
        else if (key == "--sensor") {
            const std::string v = value();
            if (v != "imu-monocular" && v != "monocular")
                usage_error("--sensor wants imu-monocular or monocular, got '" + v + "'");
            a.imu = v == "imu-monocular";
        }
        else if (key == "--gate-timeout") {
            const std::string v = value();
            if (!parse_double(v, &a.gate_timeout_s) || !(a.gate_timeout_s > 0.0))
                usage_error("--gate-timeout wants a positive number of seconds, got '" + v + "'");
        }
        else if (key == "--branch-at" || key == "--branch-frames") {
            const std::string v = value();
            long long n = 0;
            if (!parse_int(v, &n) || n < (key == "--branch-at" ? 1 : 1))
                usage_error(key + " wants a positive integer, got '" + v + "'");
            (key == "--branch-at" ? a.branch_at : a.branch_frames) = n;
        }
        else if (key == "--branch-log") a.branch_log = value();
        else if (key == "--branch-summary") a.branch_summary = value();
        else if (key == "--branch-coast") a.branch_coast = true;
        else if (key == "--branch-rule-inliers" || key == "--branch-rule-sve") {
            if (a.branch_has_rule) usage_error("one branch rule: --branch-rule-inliers or --branch-rule-sve, once");
            std::string error;
            if (!jsve_hook::parse_rule(key == "--branch-rule-sve" ? "--rule-sve" : "--rule-inliers", value(),
                                       &a.branch_rule, &error))
                usage_error(error);
            a.branch_has_rule = true;
        }
        else if (key == "--seed") {
            const std::string v = value();
            if (!parse_int(v, &a.seed) || a.seed < 0 || a.seed > 4294967294LL)
                usage_error("--seed wants an integer in [0, 2^32 - 1), got '" + v + "'");
            a.has_seed = true;
        }
        else if (key == "--rule-inliers" || key == "--rule-sve") {
            if (a.has_rule) usage_error("one rule: --rule-inliers or --rule-sve, once");
            std::string error;
            if (!jsve_hook::parse_rule(key, value(), &a.rule, &error)) usage_error(error);
            a.has_rule = true;
        }
        else if (key == "--n-features") {
            const std::string v = value();
            if (!parse_double(v, &a.rule.n_features) || !(a.rule.n_features > 0.0))
                usage_error("--n-features wants a positive number, got '" + v + "'");
        }
        else if (key == "--meta") {
            const std::string kv = value();
            const std::size_t eq = kv.find('=');
            if (eq == std::string::npos || eq == 0) usage_error("--meta wants KEY=VALUE, got '" + kv + "'");
            a.meta.emplace_back(kv.substr(0, eq), kv.substr(eq + 1));
        } else usage_error("unknown argument '" + key + "'");
    }
    if (a.vocabulary.empty() || a.settings.empty() || a.sequence.empty() || a.log.empty())
        usage_error("--vocabulary, --settings, --sequence and --log are required");
    if (a.lockstep) a.wait = false;
    if (a.branch_at > 0 && (!a.lockstep || a.branch_frames < 1 || a.branch_log.size() != a.log.size()))
        usage_error("--branch-at needs --lockstep, --branch-frames and a --branch-log as long as --log");
    if (a.branch_coast && !a.branch_has_rule) usage_error("--branch-coast needs a --branch-rule-*");
    // jsve's rules replace ORB-SLAM3's IMU_MONOCULAR success test (its IMU-stage thresholds); MONOCULAR's
    // own test and its recovery by relocalisation are another machine, which jsve does not model.
    if (!a.imu && (a.has_rule || a.branch_has_rule || a.coast))
        usage_error("--rule-*, --branch-rule-* and --coast need --sensor imu-monocular");
    if (a.keypoints && a.branch_at > 0) usage_error("--keypoints does not go with --branch-at");
    a.branch_rule.n_features = a.rule.n_features;
    return a;
}

// KEY=VALUE into the log's metadata, typed as described at the top.
void set_meta(jsve::Metadata& meta, const std::string& key, const std::string& text) {
    long long i = 0;
    double d = 0.0;
    if (text.size() >= 2 && text.front() == '"' && text.back() == '"') {
        meta.set(key, text.substr(1, text.size() - 2));  // a quoted string stays a string
    } else if (text.size() >= 2 && text.front() == '[' && text.back() == ']') {
        std::vector<long long> ints;
        std::vector<double> doubles;
        bool all_ints = true;
        std::stringstream items(text.substr(1, text.size() - 2));
        for (std::string item; std::getline(items, item, ',');) {
            item.erase(0, item.find_first_not_of(' '));
            item.erase(item.find_last_not_of(' ') + 1);
            if (parse_int(item, &i)) { ints.push_back(i); doubles.push_back(double(i)); }
            else if (parse_double(item, &d)) { all_ints = false; doubles.push_back(d); }
            else usage_error("--meta " + key + ": list item '" + item + "' is not a number");
        }
        if (all_ints) meta.set(key, std::vector<std::int64_t>(ints.begin(), ints.end()));
        else meta.set(key, doubles);
    } else if (parse_int(text, &i)) {
        meta.set(key, static_cast<std::int64_t>(i));
    } else if (text.find_first_of(".eE") != std::string::npos && parse_double(text, &d)) {
        meta.set(key, d);
    } else {
        meta.set(key, text);
    }
}

std::vector<std::vector<std::string>> read_csv(const std::string& path) {
    std::ifstream in(path);
    if (!in) usage_error("cannot read " + path);
    std::vector<std::vector<std::string>> rows;
    std::string line;
    for (int n = 1; std::getline(in, line); ++n) {
        if (!line.empty() && line.back() == '\r') line.pop_back();
        if (line.empty() || line[0] == '#') continue;
        std::vector<std::string> fields;
        std::stringstream s(line);
        for (std::string f; std::getline(s, f, ',');) fields.push_back(f);
        rows.push_back(fields);
        if (fields.empty()) usage_error(path + ":" + std::to_string(n) + ": empty row");
    }
    return rows;
}

struct Image { long long t_ns; std::string path, name; };

std::vector<Image> read_images(const std::string& dir) {
    std::vector<Image> images;
    const std::string csv = dir + "/mav0/cam0/data.csv";
    long long t = 0;
    for (const auto& row : read_csv(csv)) {
        if (row.size() < 2 || !parse_int(row[0], &t)) usage_error(csv + ": row without `t_ns,file`");
        std::string name = row[1];
        name.erase(0, name.find_first_not_of(' '));
        images.push_back({t, dir + "/mav0/cam0/data/" + name, name});
    }
    if (images.empty()) usage_error(csv + ": no images");
    return images;
}

std::vector<ORB_SLAM3::IMU::Point> read_imu(const std::string& dir) {
    std::vector<ORB_SLAM3::IMU::Point> samples;
    const std::string csv = dir + "/mav0/imu0/data.csv";
    for (const auto& row : read_csv(csv)) {
        long long t = 0;
        double v[6];
        bool ok = row.size() >= 7 && parse_int(row[0], &t);
        for (int k = 0; ok && k < 6; ++k) ok = parse_double(row[k + 1], &v[k]);
        if (!ok) usage_error(csv + ": row without `t_ns,wx,wy,wz,ax,ay,az`");
        samples.emplace_back(float(v[3]), float(v[4]), float(v[5]), float(v[0]), float(v[1]), float(v[2]),
                             double(t) * 1e-9);
    }
    if (samples.empty()) usage_error(csv + ": no samples");
    return samples;
}

// The mask of every image (--masks): DIR/mav0/cam0/masks/<the image's name, extension .png>. A missing
// one stops the run before it starts (exit 2, naming it): a frame without its mask is not masked.
std::vector<std::string> mask_paths(const std::string& dir, const std::vector<Image>& images) {
    std::vector<std::string> paths;
    paths.reserve(images.size());
    for (const Image& image : images) {
        const std::size_t dot = image.name.find_last_of('.');
        paths.push_back(dir + "/" + kMaskFolder + "/" + image.name.substr(0, dot) + ".png");
        if (access(paths.back().c_str(), R_OK) != 0) usage_error("--masks: no mask " + paths.back());
    }
    return paths;
}

// The instance map of one frame, checked: 16-bit, one channel, the image's size.
cv::Mat read_mask(const std::string& path, const cv::Mat& image) {
    cv::Mat mask = cv::imread(path, cv::IMREAD_UNCHANGED);
    if (mask.empty()) throw BadInput("cannot read mask " + path);
    if (mask.type() != CV_16UC1)
        throw BadInput("mask " + path + ": not a 16-bit one-channel instance map (pixel = obj_id)");
    if (mask.size() != image.size())
        throw BadInput("mask " + path + ": " + std::to_string(mask.cols) + " x " + std::to_string(mask.rows) +
                       " px, the image " + std::to_string(image.cols) + " x " + std::to_string(image.rows));
    return mask;
}

double seconds_since(std::chrono::steady_clock::time_point start) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// The driver ends with the process that started it: a `jsve frontend run` killed with SIGKILL leaves no
// run writing behind it (its resumed command would otherwise run the same log twice).
void die_with_parent() {
    const pid_t parent = getppid();
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent) std::_Exit(1);  // the parent died before the request took effect
}

// Lockstep removes what makes the heap's addresses differ between runs, since ORB-SLAM3 orders
// keyframes and map points by address: the process re-executes itself once without address-space
// randomisation (personality(2); where the kernel refuses, the run goes on with it and the summary
// says `aslr: true`), and every thread allocates from one malloc arena (glibc's tunables), in the order
// lockstep fixes.
bool fix_addresses(char** argv) {
    const int current = personality(0xffffffff);
    if (current != -1 && !(current & ADDR_NO_RANDOMIZE) && !std::getenv("JSVE_NO_REEXEC")) {
        if (personality(current | ADDR_NO_RANDOMIZE) != -1) {
            setenv("JSVE_NO_REEXEC", "1", 1);
            setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=1", 1);
            execv("/proc/self/exe", argv);  // returns only on failure: go on with randomisation
        }
    }
    mallopt(M_ARENA_MAX, 1);
    const int now = personality(0xffffffff);
    return now == -1 || !(now & ADDR_NO_RANDOMIZE);
}

// Thread stacks for a lockstep branch: a thread's TLS vector is allocated on the heap with a new stack
// and kept with a cached one. Threads started and joined here leave their stacks in glibc's cache, so
// that the threads the run starts later (LocalMapping, LoopClosing, global BA; in a branch, the child's
// two workers) take cached stacks and allocate nothing: a branch's heap stays its parent's.
void fill_stack_cache(int threads) {
    std::vector<pthread_t> started(threads);
    for (pthread_t& t : started) pthread_create(&t, nullptr, [](void*) -> void* { return nullptr; }, nullptr);
    for (pthread_t& t : started) pthread_join(t, nullptr);
}

double cpu_seconds() {
    rusage usage{};
    getrusage(RUSAGE_SELF, &usage);
    return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec + 1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

}  // namespace

int main(int argc, char** argv) {
    const auto started = std::chrono::steady_clock::now();
    die_with_parent();
    const Args args = parse_args(argc, argv);
    const bool aslr = args.lockstep ? fix_addresses(argv) : true;
    if (args.lockstep) {
        cv::setNumThreads(0);  // OpenCV's workers would allocate concurrently
        fill_stack_cache(4);
    }
    // glibc's srand treats seed 0 as 1: seed S seeds S + 1, so that every S draws its own stream and S = 0
    // draws what ORB-SLAM3's own SeedRandOnce(0) does.
    if (args.has_seed) DUtils::Random::SeedRandOnce(static_cast<int>(static_cast<unsigned>(args.seed + 1)));
    const std::vector<Image> images = read_images(args.sequence);
    const std::vector<ORB_SLAM3::IMU::Point> imu = args.imu ? read_imu(args.sequence) : std::vector<ORB_SLAM3::IMU::Point>();
    const std::vector<std::string> masks = args.masks ? mask_paths(args.sequence, images) : std::vector<std::string>();
    const std::string mask_source = std::string("in-loop png:DATASET/") + kMaskFolder + " classes=[1, 2]";

    jsve::Metadata meta;
    for (const auto& [key, value] : args.meta) set_meta(meta, key, value);
    meta.set("sensor", args.imu ? "imu_monocular" : "monocular");
    if (args.masks) meta.set("masks", mask_source);
    std::string error;
    if (!jsve_hook::open_log(args.log, meta, args.overwrite, &error)) {
        std::cerr << "jsve_orbslam3: cannot open the log: " << error << "\n";
        return 2;
    }
    if (args.keypoints) {  // the run id of the log, as jsve.io's reader matches them
        jsve::Metadata kp;
        for (const auto& [key, value] : args.meta)
            if (key == "sequence" || key == "run" || key == "disturbance" || key == "level" || key == "frontend")
                set_meta(kp, key, value);
        if (args.masks) kp.set("masks", mask_source);
        if (!jsve_hook::open_keypoints(jsve::keypoints_path(args.log), kp, args.overwrite, &error)) {
            std::cerr << "jsve_orbslam3: cannot write the keypoints: " << error << "\n";
            return 2;
        }
    }
    if (args.masks) jsve_hook::enable_masks();

    if (args.coast && !args.has_rule) usage_error("--coast needs --rule-inliers or --rule-sve");
    if (args.lockstep) jsve_hook::enable_lockstep(args.gate_timeout_s);
    const double setup_seconds = seconds_since(started);
    const auto system_start = std::chrono::steady_clock::now();
    ORB_SLAM3::System slam(args.vocabulary, args.settings,
                           args.imu ? ORB_SLAM3::System::IMU_MONOCULAR : ORB_SLAM3::System::MONOCULAR, false);
    const double system_seconds = seconds_since(system_start);
    if (args.has_rule) jsve_hook::set_rule(args.rule, args.coast);
    // IMU samples up to the first image start nothing: ORB-SLAM3's first frame has no preintegration.
    std::size_t next = 0;
    while (next < imu.size() && imu[next].t <= double(images[0].t_ns) * 1e-9) ++next;
    double track_seconds = 0.0, decode_seconds = 0.0, pace_seconds = 0.0;
    bool ever_tracked = false, gates_open = true, in_branch = false;
    int status = 0, branch_exit = 0;
    std::size_t frames_done = 0, last = images.size();
    double branch_seconds = 0.0;
    const std::string* summary_path = &args.summary;  // a pointer: switching to the branch's allocates nothing
    try {
        for (std::size_t i = 0; i < last && gates_open; ++i) {
            if (!in_branch && args.branch_at >= 0 && i == static_cast<std::size_t>(args.branch_at)) {
                const auto fork_start = std::chrono::steady_clock::now();
                const int pid = jsve_hook::fork_parked();
                if (pid == 0) {  // the branch: its own log, rule and summary, W frames from here
                    in_branch = true;
                    last = std::min(images.size(), i + static_cast<std::size_t>(args.branch_frames));
                    track_seconds = decode_seconds = 0.0;
                    frames_done = 0;
                    summary_path = &args.branch_summary;
                    if (args.branch_has_rule) jsve_hook::set_rule(args.branch_rule, args.branch_coast);
                    if (!jsve_hook::continue_log_as(args.branch_log, &error)) {
                        std::cerr << "jsve_orbslam3: branch: " << error << "\n";
                        std::_Exit(1);
                    }
                } else if (pid > 0) {
                    int wait_status = 0;
                    waitpid(pid, &wait_status, 0);
                    branch_exit = WIFEXITED(wait_status) ? WEXITSTATUS(wait_status) : -WTERMSIG(wait_status);
                    branch_seconds = seconds_since(fork_start);
                } else {
                    std::cerr << "jsve_orbslam3: cannot branch at frame " << i << "\n";
                    branch_exit = -1000;
                }
            }
            const auto decode_start = std::chrono::steady_clock::now();
            const cv::Mat im = cv::imread(images[i].path, cv::IMREAD_UNCHANGED);
            decode_seconds += seconds_since(decode_start);
            if (im.empty()) throw std::runtime_error("cannot read image " + images[i].path);
            const double t = double(images[i].t_ns) * 1e-9;
            std::vector<ORB_SLAM3::IMU::Point> between;
            if (i > 0)
                while (next < imu.size() && imu[next].t <= t) between.push_back(imu[next++]);
            cv::Mat mask;  // this frame's instance map, held until TrackMonocular returns
            jsve::InstanceMask view;
            if (args.masks) {
                const auto mask_start = std::chrono::steady_clock::now();
                mask = read_mask(masks[i], im);
                decode_seconds += seconds_since(mask_start);
                view = {mask.ptr<std::uint16_t>(), mask.cols, mask.rows, static_cast<std::ptrdiff_t>(mask.step1())};
            }
            jsve_hook::begin_input(im.cols, im.rows, view);
            const auto start = std::chrono::steady_clock::now();
            slam.TrackMonocular(im, t, between, images[i].path);
            const double took = seconds_since(start);
            jsve_hook::end_input();
            track_seconds += took;
            gates_open = jsve_hook::settle_frame();
            // Local mapping runs in its own thread: without waiting out the frame interval it would fall
            // behind the tracker, which a live run never lets it do.
            if (args.wait && i + 1 < images.size()) {
                const double gap = double(images[i + 1].t_ns - images[i].t_ns) * 1e-9;
                const auto pace = std::chrono::steady_clock::now();
                if (took < gap) std::this_thread::sleep_for(std::chrono::duration<double>(gap - took));
                pace_seconds += seconds_since(pace);
            }
            ever_tracked = ever_tracked || slam.GetTrackingState() == 2;  // OK
            ++frames_done;
        }
    } catch (const BadInput& e) {
        std::cerr << "jsve_orbslam3: " << e.what() << "\n";
        status = 2;
    } catch (const std::exception& e) {
        std::cerr << "jsve_orbslam3: " << args.sequence << ": " << e.what() << "\n";
        status = 1;
    }
    const jsve_hook::Lockstep& gates = jsve_hook::lockstep();
    auto write_summary = [&](bool save, bool trailer, double finish_seconds) {
        if (summary_path->empty()) return;
        const jsve_hook::HookState& hook = jsve_hook::state();
        std::ofstream out(*summary_path);
        out << "{\"frames\": " << images.size() << ", \"frames_done\": " << frames_done
            << ", \"track_seconds\": " << track_seconds << ", \"hook_seconds\": " << hook.log_seconds
            << ", \"imu_invalid_frames\": " << hook.imu_invalid_frames
            << ", \"pose_invalid_frames\": " << hook.pose_invalid_frames
            << ", \"keyframes_at_end\": " << hook.keyframes << ", \"ever_tracked\": " << (ever_tracked ? "true" : "false")
            << ", \"sensor\": \"" << (args.imu ? "imu-monocular" : "monocular") << "\""
            << ", \"masks\": " << (args.masks ? "true" : "false")
            << ", \"masked_keypoints\": " << jsve_hook::mask_state().total_removed
            << ", \"keypoints\": " << (args.keypoints ? "true" : "false")
            << ", \"keypoint_inlier_mismatch_frames\": " << hook.keypoint_inlier_mismatches
            << ", \"trajectory_saved\": " << (save ? "true" : "false")
            << ", \"trailer_written\": " << (trailer ? "true" : "false") << ", \"status\": " << status
            << ", \"mode\": \"" << (args.lockstep ? "lockstep" : (args.wait ? "paced" : "no-wait")) << "\""
            << ", \"seed\": " << (args.has_seed ? std::to_string(args.seed) : std::string("null"))
            << ", \"aslr\": " << (aslr ? "true" : "false") << ", \"gates_open\": " << (gates_open ? "true" : "false")
            << ", \"branch\": " << (args.branch_at < 0 ? std::string("null") :
                "{\"at\": " + std::to_string(args.branch_at) + ", \"frames\": " + std::to_string(args.branch_frames) +
                ", \"in_branch\": " + (in_branch ? "true" : "false") + ", \"exit\": " + std::to_string(branch_exit) +
                ", \"seconds\": " + std::to_string(branch_seconds) + "}")
            << ", \"time\": {\"setup_s\": " << setup_seconds << ", \"system_s\": " << system_seconds
            << ", \"decode_s\": " << decode_seconds << ", \"track_s\": " << track_seconds
            << ", \"settle_s\": " << gates.settle_s << ", \"local_mapping_s\": " << gates.busy_s[jsve_hook::kLocalMapping]
            << ", \"loop_closing_s\": " << gates.busy_s[jsve_hook::kLoopClosing] << ", \"gba_wait_s\": " << gates.gba_wait_s
            << ", \"pace_s\": " << pace_seconds << ", \"finish_s\": " << finish_seconds
            << ", \"main_s\": " << seconds_since(started) << ", \"cpu_s\": " << cpu_seconds() << "}}\n";
    };
    if (!gates_open) {
        // A worker never parked again: the run cannot go on in lockstep, and its threads may never end.
        status = 3;
        std::cerr << "jsve_orbslam3: a lockstep gate did not open within " << args.gate_timeout_s << " s\n";
        write_summary(false, false, 0.0);
        std::_Exit(3);
    }
    const auto finish_start = std::chrono::steady_clock::now();
    slam.Shutdown();
    // The trailer (format v3) records what SaveTrajectoryEuRoC reads, once LocalMapping and LoopClosing
    // have finished; a run without it still closes its log (`trailer_written` false in the summary).
    const bool trailer = status == 0 && jsve_hook::write_trailer(120.0, &error);
    if (status == 0 && !trailer) std::cerr << "jsve_orbslam3: no trailer: " << error << "\n";
    if (status == 0 && args.masks && !jsve_hook::write_masks_trailer(mask_source, &error)) {
        std::cerr << "jsve_orbslam3: cannot write the masks trailer: " << error << "\n";
        status = 1;
    }
    if (status == 0 && !jsve_hook::close_log(&error)) {
        std::cerr << "jsve_orbslam3: cannot close the log: " << error << "\n";
        status = 1;
    }
    // SaveTrajectoryEuRoC crashes ORB-SLAM3 when the active map has no keyframe (never built, or reset
    // at the end of the run): skip it then, and write the summary first, so that it says so.
    const bool save = status == 0 && ever_tracked && jsve_hook::state().keyframes > 0 && !args.trajectory.empty() &&
                      !in_branch;
    write_summary(save, trailer, seconds_since(finish_start));
    if (in_branch) {  // the parent owns everything else this process inherited
        std::fflush(nullptr);
        std::_Exit(status);
    }
    if (save) slam.SaveTrajectoryEuRoC(args.trajectory);
    return status;
}
