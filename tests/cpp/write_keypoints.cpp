// A keypoint side file through jsve_keypoints.hpp; tests/test_frontend_keypoints.py reads it back with
// jsve.io.read_keypoints.
//
// usage: write_keypoints OUT.csv DIR < rows
//   rows: `t_ns xbits ybits uxbits uybits octave inlier`, the four coordinates as the bits of floats
//   (uint32), written to OUT.csv (metadata below). Then, in DIR, files the writer must refuse or keep
//   partial; on stdout one line per case, `name status`, and `path LOG SIDE` for keypoints_path.
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <iostream>
#include <limits>
#include <string>

#include "jsve_keypoints.hpp"

static float from_bits(std::uint32_t bits) {
    float f;
    std::memcpy(&f, &bits, sizeof f);
    return f;
}

static jsve::Metadata metadata() {
    jsve::Metadata meta;
    meta.set("sequence", "V101").set("run", 3).set("disturbance", "blur").set("level", 20.0);
    meta.set("image_size", {752, 480}).set("image_bounds", {-1.5, 760.25, 0.0, 481.0}).set("frontend", "test");
    return meta;
}

static void report(const char* name, jsve::Status status) { std::printf("%s %s\n", name, jsve::to_string(status)); }

// Each case writes a good row first, then the bad one, then tries one more row and close().
static void refusals(const std::string& dir) {
    jsve::KeypointOptions options;
    options.on_error = jsve::OnError::kReturn;
    const float nan = std::numeric_limits<float>::quiet_NaN();
    struct Case { const char* name; std::int64_t t_ns; float x; int octave; };
    const Case cases[] = {{"nan_x", 20, nan, 0}, {"negative_octave", 20, 1.0f, -1}, {"stamp_back", 5, 1.0f, 0}};
    for (const Case& c : cases) {
        jsve::KeypointWriter w(dir + "/" + c.name + ".keypoints.csv", metadata(), options);
        w.write(10, 1.0f, 2.0f, 1.0f, 2.0f, 0, true);
        report(c.name, w.write(c.t_ns, c.x, 2.0f, 1.0f, 2.0f, c.octave, false));
        report((std::string(c.name) + "_then_write").c_str(), w.write(30, 1.0f, 2.0f, 1.0f, 2.0f, 0, false));
        report((std::string(c.name) + "_then_close").c_str(), w.close());
    }
    jsve::Metadata no_sequence;
    no_sequence.set("run", 0).set("image_size", {752, 480});
    report("no_sequence", jsve::KeypointWriter().open(dir + "/x.csv", no_sequence, options));
    jsve::Metadata bad_bounds = metadata();
    bad_bounds.set("image_bounds", {10.0, 10.0, 0.0, 480.0});
    report("bad_bounds", jsve::KeypointWriter().open(dir + "/x.csv", bad_bounds, options));
    jsve::Metadata bad_size = metadata();
    bad_size.set("image_size", {752, 0});
    report("bad_size", jsve::KeypointWriter().open(dir + "/x.csv", bad_size, options));
    {
        jsve::KeypointWriter empty(dir + "/empty.keypoints.csv", metadata(), options);
        report("empty", empty.close());
    }
    report("exists", jsve::KeypointWriter().open(dir + "/empty.keypoints.csv", metadata(), options));
    jsve::KeypointOptions replace = options;
    replace.overwrite = true;
    jsve::KeypointWriter again(dir + "/empty.keypoints.csv", metadata(), replace);
    report("overwrite", again.close());
    try {
        jsve::KeypointWriter thrown(dir + "/thrown.keypoints.csv", metadata());
        thrown.write(10, nan, 0.0f, 0.0f, 0.0f, 0, false);
        std::printf("thrown none\n");
    } catch (const jsve::LogError& e) {
        report("thrown", e.status());
    }
    std::printf("path %s %s\n", "runs/r7.csv", jsve::keypoints_path("runs/r7.csv").c_str());
    std::printf("path %s %s\n", "runs/r7", jsve::keypoints_path("runs/r7").c_str());
}

int main(int argc, char** argv) {
    if (argc != 3) return 2;
    jsve::KeypointWriter w(argv[1], metadata());
    long long t_ns;
    std::uint32_t x, y, ux, uy;
    int octave, inlier;
    while (std::cin >> t_ns >> x >> y >> ux >> uy >> octave >> inlier)
        w.write(t_ns, from_bits(x), from_bits(y), from_bits(ux), from_bits(uy), octave, inlier != 0);
    w.close();
    refusals(argv[2]);
    return 0;
}
