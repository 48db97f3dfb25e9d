// Writes a format-v3 log with the keyframe columns and a trailer, then tries what the writer must
// refuse; tests/test_log_v3.py reads the log back and checks every value.
//
// usage: write_keyframes OUT.csv
//   frames k = 0..5: events = 1 << k (k < 5), traj on even k, ref_kf = 10 + k except k = 3 (-1, no
//   rel_*), rel_p = (k, -k, 0.5), rel_q = (cos a, 0, 0, sin a) with a = 0.1 k; then the trailer
//   `demo {"x":[1,2]}`. On stdout one line per refusal: the status name of each attempt below.
#include <cmath>
#include <cstdio>
#include <string>

#include "jsve_log.hpp"

int main(int argc, char** argv) {
    if (argc != 2) return 2;
    const std::string out = argv[1];
    jsve::Metadata meta;
    meta.set("sequence", "KF").set("run", 0).set("fps", 20);
    jsve::Options options;
    options.keyframes = true;
    options.on_error = jsve::OnError::kReturn;
    jsve::LogWriter log(out, meta, options);
    for (int k = 0; k < 6; ++k) {
        jsve::Frame f;
        f.t_ns = 1000 + k;
        f.state = 2;
        f.events = k < 5 ? (1u << k) : 0u;
        f.ref_kf = k == 3 ? -1 : 10 + k;
        f.traj = k % 2 == 0 && f.ref_kf >= 0;
        f.rel_p[0] = k, f.rel_p[1] = -k, f.rel_p[2] = 0.5;
        f.rel_q[0] = std::cos(0.1 * k), f.rel_q[3] = std::sin(0.1 * k);
        if (log.write(f) != jsve::Status::kOk) {
            std::fprintf(stderr, "%s\n", log.last_error().c_str());
            return 1;
        }
    }
    // Refusals, each on a fresh writer (a refusal fails the writer).
    auto attempt = [&](const char* name, auto&& act) {
        jsve::LogWriter w(out + "." + name, meta, options);
        jsve::Frame ok;
        ok.t_ns = 1;
        w.write(ok);
        std::printf("%s %s\n", name, jsve::to_string(act(w)));
        w.abandon();
    };
    attempt("traj_without_ref", [](jsve::LogWriter& w) {
        jsve::Frame f;
        f.t_ns = 2, f.traj = true;
        return w.write(f);
    });
    attempt("unknown_event", [](jsve::LogWriter& w) {
        jsve::Frame f;
        f.t_ns = 2, f.events = 1u << 8;
        return w.write(f);
    });
    attempt("rel_not_unit", [](jsve::LogWriter& w) {
        jsve::Frame f;
        f.t_ns = 2, f.ref_kf = 4, f.rel_q[0] = 0.5;
        return w.write(f);
    });
    attempt("frame_after_trailer", [](jsve::LogWriter& w) {
        w.trailer("t", "{}");
        jsve::Frame f;
        f.t_ns = 2;
        return w.write(f);
    });
    attempt("bad_trailer_key", [](jsve::LogWriter& w) { return w.trailer("Bad-Key", "{}"); });
    attempt("multiline_trailer", [](jsve::LogWriter& w) { return w.trailer("t", "{\n}"); });
    if (log.trailer("demo", "{\"x\":[1,2]}") != jsve::Status::kOk || log.close() != jsve::Status::kOk) {
        std::fprintf(stderr, "%s\n", log.last_error().c_str());
        return 1;
    }
    return 0;
}
