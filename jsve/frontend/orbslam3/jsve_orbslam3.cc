// jsve_orbslam3: runs ORB-SLAM3 v1.0 (IMU_MONOCULAR) over one EuRoC-format sequence and writes a
// jsve tracking log through the hook (jsve_orbslam3_hook.hpp), plus ORB-SLAM3's own trajectory.
//
//   jsve_orbslam3 --vocabulary VOC.txt --settings EuRoC.yaml --sequence DIR --log OUT.csv
//                 [--trajectory OUT.txt] [--summary OUT.json] [--meta KEY=VALUE]... [--overwrite]
//                 [--no-wait]   (default: frames paced at the camera's rate, as ORB-SLAM3's examples do)
//                 [--rule-inliers IMU_INIT,NOT_INIT,RELOC,RECOVERY [--coast]]   (default: ORB-SLAM3's test)
//                 [--rule-sve INPUTS,W_A,U_B,P,Q,RHO,IMU_INIT,NOT_INIT,RELOC,RECOVERY [--coast]]
//                 [--n-features N]   (ORBextractor.nFeatures, S_a of the authors' Eq.1; default 1000)
// INPUTS of an SVE rule: jsve, authors-eq1 or authors-option1 (jsve.core._sve.INPUTS; the authors'
// inputs need P = Q = 1).
//
// DIR holds mav0/cam0/data.csv (`t_ns,file`), mav0/cam0/data/<file> and mav0/imu0/data.csv (`t_ns,
// wx,wy,wz,ax,ay,az`, EuRoC's column order). --meta values are typed like JSON scalars and lists:
// `run=3` an integer, `fps=20.0` a float, `image_size=[752,480]` a list, `key="..."` a string (so a
// hash of digits stays one), anything else a string too.
// Exit status: 0 on success, 1 when the run or its log failed (the log then stays `.partial`), 2 on
// bad arguments or input. It is jsve's own program, not one of ORB-SLAM3's examples.
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

#include <opencv2/imgcodecs.hpp>

#include "ImuTypes.h"
#include "System.h"
#include "jsve_orbslam3_hook.hpp"

namespace {

struct Args {
    std::string vocabulary, settings, sequence, log, trajectory, summary;
    std::vector<std::pair<std::string, std::string>> meta;
    bool overwrite = false;
    bool wait = true;  // pace frames at the camera's rate, as a live camera (and ORB-SLAM3's examples) do
    bool has_rule = false, coast = false;
    jsve_hook::Rule rule;
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

struct Image { long long t_ns; std::string path; };

std::vector<Image> read_images(const std::string& dir) {
    std::vector<Image> images;
    const std::string csv = dir + "/mav0/cam0/data.csv";
    long long t = 0;
    for (const auto& row : read_csv(csv)) {
        if (row.size() < 2 || !parse_int(row[0], &t)) usage_error(csv + ": row without `t_ns,file`");
        std::string name = row[1];
        name.erase(0, name.find_first_not_of(' '));
        images.push_back({t, dir + "/mav0/cam0/data/" + name});
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

}  // namespace

int main(int argc, char** argv) {
    const Args args = parse_args(argc, argv);
    const std::vector<Image> images = read_images(args.sequence);
    const std::vector<ORB_SLAM3::IMU::Point> imu = read_imu(args.sequence);

    jsve::Metadata meta;
    for (const auto& [key, value] : args.meta) set_meta(meta, key, value);
    std::string error;
    if (!jsve_hook::open_log(args.log, meta, args.overwrite, &error)) {
        std::cerr << "jsve_orbslam3: cannot open the log: " << error << "\n";
        return 2;
    }

    if (args.coast && !args.has_rule) usage_error("--coast needs --rule-inliers or --rule-sve");
    ORB_SLAM3::System slam(args.vocabulary, args.settings, ORB_SLAM3::System::IMU_MONOCULAR, false);
    if (args.has_rule) jsve_hook::set_rule(args.rule, args.coast);
    // IMU samples up to the first image start nothing: ORB-SLAM3's first frame has no preintegration.
    std::size_t next = 0;
    while (next < imu.size() && imu[next].t <= double(images[0].t_ns) * 1e-9) ++next;
    double track_seconds = 0.0;
    bool ever_tracked = false;
    int status = 0;
    try {
        for (std::size_t i = 0; i < images.size(); ++i) {
            const cv::Mat im = cv::imread(images[i].path, cv::IMREAD_UNCHANGED);
            if (im.empty()) throw std::runtime_error("cannot read image " + images[i].path);
            const double t = double(images[i].t_ns) * 1e-9;
            std::vector<ORB_SLAM3::IMU::Point> between;
            if (i > 0)
                while (next < imu.size() && imu[next].t <= t) between.push_back(imu[next++]);
            const auto start = std::chrono::steady_clock::now();
            slam.TrackMonocular(im, t, between, images[i].path);
            const double took = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
            track_seconds += took;
            // Local mapping runs in its own thread: without waiting out the frame interval it would fall
            // behind the tracker, which a live run never lets it do.
            if (args.wait && i + 1 < images.size()) {
                const double gap = double(images[i + 1].t_ns - images[i].t_ns) * 1e-9;
                if (took < gap) std::this_thread::sleep_for(std::chrono::duration<double>(gap - took));
            }
            ever_tracked = ever_tracked || slam.GetTrackingState() == 2;  // OK
        }
    } catch (const std::exception& e) {
        std::cerr << "jsve_orbslam3: " << args.sequence << ": " << e.what() << "\n";
        status = 1;
    }
    const double log_seconds = jsve_hook::state().log_seconds;
    slam.Shutdown();
    // The trailer (format v3) records what SaveTrajectoryEuRoC reads, once LocalMapping and LoopClosing
    // have finished; a run without it still closes its log (`trailer_written` false in the summary).
    const bool trailer = status == 0 && jsve_hook::write_trailer(120.0, &error);
    if (status == 0 && !trailer) std::cerr << "jsve_orbslam3: no trailer: " << error << "\n";
    if (status == 0 && !jsve_hook::close_log(&error)) {
        std::cerr << "jsve_orbslam3: cannot close the log: " << error << "\n";
        status = 1;
    }
    // SaveTrajectoryEuRoC crashes ORB-SLAM3 when the active map has no keyframe (never built, or reset
    // at the end of the run): skip it then, and write the summary first, so that it says so.
    const jsve_hook::HookState& hook = jsve_hook::state();
    const bool save = status == 0 && ever_tracked && hook.keyframes > 0 && !args.trajectory.empty();
    if (!args.summary.empty()) {
        std::ofstream out(args.summary);
        out << "{\"frames\": " << images.size() << ", \"track_seconds\": " << track_seconds
            << ", \"hook_seconds\": " << log_seconds << ", \"imu_invalid_frames\": " << hook.imu_invalid_frames
            << ", \"pose_invalid_frames\": " << hook.pose_invalid_frames
            << ", \"keyframes_at_end\": " << hook.keyframes << ", \"ever_tracked\": " << (ever_tracked ? "true" : "false")
            << ", \"trajectory_saved\": " << (save ? "true" : "false")
            << ", \"trailer_written\": " << (trailer ? "true" : "false") << ", \"status\": " << status << "}\n";
    }
    if (save) slam.SaveTrajectoryEuRoC(args.trajectory);
    return status;
}
