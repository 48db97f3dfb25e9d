// Exercises the error policy of jsve_log.hpp: what is rejected, with which Status, and which files
// are left on disk. Prints one "PASS name" or "FAIL name: detail" line per check and exits with
// the number of failures; tests/test_frontend.py runs it and then reads the files it leaves.
//
// usage: check_policy DIR        (DIR must exist and be empty)

#include "jsve_log.hpp"

#include <cmath>
#include <cstdio>
#include <limits>
#include <string>

namespace {

int g_failures = 0;
std::string g_dir;

void report(const std::string& name, bool ok, const std::string& detail = "") {
    if (ok) {
        std::printf("PASS %s\n", name.c_str());
    } else {
        ++g_failures;
        std::printf("FAIL %s: %s\n", name.c_str(), detail.c_str());
    }
}

bool exists(const std::string& path) {
    std::FILE* f = std::fopen(path.c_str(), "rb");
    if (f != nullptr) std::fclose(f);
    return f != nullptr;
}

int count_lines(const std::string& path) {
    std::FILE* f = std::fopen(path.c_str(), "rb");
    if (f == nullptr) return -1;
    int n = 0;
    for (int c; (c = std::fgetc(f)) != EOF;)
        if (c == '\n') ++n;
    std::fclose(f);
    return n;
}

jsve::Metadata good_meta() {
    jsve::Metadata m;
    m.set("sequence", "V1_01").set("run", 3).set("fps", 20.0);
    return m;
}

jsve::Options returning(bool gt = false, bool world = false) {
    jsve::Options o;
    o.on_error = jsve::OnError::kReturn;
    o.ground_truth = gt;
    o.world_frame = world;
    return o;
}

// A valid frame; the first frame of a log has no preintegration (imu_dt 0, identity deltas).
jsve::Frame good_frame(std::int64_t t_ns, bool first = false) {
    jsve::Frame f;
    f.t_ns = t_ns;
    f.state = 2;
    f.imu_init = true;
    f.map_id = 7;
    f.imu_ba2 = true;
    f.n_extracted = 100;
    f.n_inliers = 40;
    f.n_frustum = 80;
    f.bins[0] = 60;
    f.bins[63] = 40;
    f.imu_dt = first ? 0.0 : 0.05;
    return f;
}

std::string path(const std::string& name) { return g_dir + "/" + name; }

// Writes two good frames, then `bad`; the bad one must be rejected with `expected` and fail the
// writer, leaving `<name>.partial` on disk and no `<name>`. A non-empty `message` must be part of
// the reason check() gives and of the writer's error.
void rejected(const std::string& name, const jsve::Frame& bad, jsve::Status expected, bool gt = false,
              bool world = false, const std::string& message = "") {
    const std::string p = path(name + ".csv");
    jsve::LogWriter w;
    jsve::Status s = w.open(p, good_meta(), returning(gt, world));
    s = (s == jsve::Status::kOk) ? w.write(good_frame(1000, true)) : s;
    s = (s == jsve::Status::kOk) ? w.write(good_frame(2000)) : s;
    if (s != jsve::Status::kOk) {
        report(name, false, "good frames refused: " + w.last_error());
        return;
    }
    std::string why;
    const jsve::Status checked = w.check(bad, &why);
    const jsve::Status got = w.write(bad);
    const std::string error = w.last_error();
    const bool said = message.empty() || (why.find(message) != std::string::npos &&
                                          error.find("frame 2 rejected: " + message) != std::string::npos);
    const bool poisoned = w.failed() && w.write(good_frame(9000)) == jsve::Status::kFailed;
    const jsve::Status closed = w.close();
    const bool ok = got == expected && checked == expected && !why.empty() && said && poisoned &&
                    closed == jsve::Status::kFailed && exists(p + ".partial") && !exists(p) && !w.is_open();
    report(name, ok,
           std::string("write=") + jsve::to_string(got) + " check=" + jsve::to_string(checked) +
               " close=" + jsve::to_string(closed) + " why=" + why + " msg=" + error);
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: %s DIR\n", argv[0]);
        return 2;
    }
    g_dir = argv[1];
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const double inf = std::numeric_limits<double>::infinity();

    {
        jsve::Frame f = good_frame(3000);
        f.vis_p[1] = nan;
        rejected("nan_position", f, jsve::Status::kNonFinite);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.imu_dv[2] = -inf;
        rejected("inf_velocity_delta", f, jsve::Status::kNonFinite);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.gt_q[0] = nan;
        rejected("nan_ground_truth", f, jsve::Status::kNonFinite, /*gt=*/true);
    }
    rejected("repeated_stamp", good_frame(2000), jsve::Status::kNonIncreasingStamp);
    rejected("earlier_stamp", good_frame(1500), jsve::Status::kNonIncreasingStamp);
    {
        jsve::Frame f = good_frame(3000);
        f.state = 6;
        rejected("state_out_of_range", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.n_frustum = -1;
        rejected("negative_count", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.map_id = -1;
        rejected("negative_map_id", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.imu_init = false;  // imu_ba2 stays true
        rejected("imu_ba2_without_imu_init", f, jsve::Status::kOutOfRange);
    }
    for (const int state : {2, 3, 5}) {  // OK, RECENTLY_LOST, OK_KLT: the front-end has a pose
        jsve::Frame f = good_frame(3000);
        f.state = state;
        f.has_pose = false;
        rejected("no_pose_in_state_" + std::to_string(state), f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.bins[5] = -2;
        rejected("negative_bin", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.bins[7] = 1;  // 101 binned keypoints, 100 extracted
        rejected("bins_exceed_extracted", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.n_inliers = 101;
        rejected("inliers_exceed_extracted", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.vis_q[0] = 1.00001;
        rejected("non_unit_quaternion", f, jsve::Status::kOutOfRange);
    }
    {
        jsve::Frame f = good_frame(3000);
        f.imu_dt = -1e-9;
        rejected("negative_imu_dt", f, jsve::Status::kOutOfRange);
    }
    // The world_* columns (Options::world_frame): finite, within float32's range, world_q a unit
    // quaternion, world_s > 0; checked on frames with or without a pose.
    {
        jsve::Frame f = good_frame(3000);
        f.world_q[0] = 0.5;
        rejected("world_non_unit_quaternion", f, jsve::Status::kOutOfRange, false, true,
                 "world_q has norm 0.5, not 1 (wxyz unit quaternion)");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_s = 0.0;
        rejected("world_scale_zero", f, jsve::Status::kOutOfRange, false, true, "world_s 0.0 is not positive");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_s = -2.0;
        rejected("world_scale_negative", f, jsve::Status::kOutOfRange, false, true, "world_s -2.0 is not positive");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_s = -0.0;
        rejected("world_scale_negative_zero", f, jsve::Status::kOutOfRange, false, true,
                 "world_s -0.0 is not positive");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_s = nan;
        rejected("world_scale_nan", f, jsve::Status::kNonFinite, false, true, "world_s[0] is nan");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_t[1] = nan;
        rejected("world_translation_nan", f, jsve::Status::kNonFinite, false, true, "world_t[1] is nan");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.state = 4;  // LOST, without a pose: the world frame is still written, so still checked
        f.has_pose = false;
        f.world_t[2] = -inf;
        rejected("world_translation_inf_without_pose", f, jsve::Status::kNonFinite, false, true,
                 "world_t[2] is -inf");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_t[0] = 1e39;
        rejected("world_translation_beyond_float32", f, jsve::Status::kOutOfRange, false, true,
                 "world_t[0] is 1e+39, beyond float32's range");
    }
    {
        jsve::Frame f = good_frame(3000);
        f.world_q[3] = nan;
        rejected("world_quaternion_nan", f, jsve::Status::kNonFinite, /*gt=*/true, /*world=*/true,
                 "world_q[3] is nan");
    }

    {
        jsve::Frame f = good_frame(3000);
        f.imu_dt = 0.0;  // repeated below for the first frame, where it is required
        f.imu_dp[2] = 1e-12;
        const std::string p = path("first_frame_delta.csv");
        jsve::LogWriter w(p, good_meta(), returning());
        const jsve::Status s = w.write(f);
        report("first_frame_needs_no_preintegration",
               s == jsve::Status::kOutOfRange && w.close() == jsve::Status::kFailed && exists(p + ".partial"),
               w.last_error());
    }
    {  // has_gt = false leaves that frame's seven gt_* fields empty, and they are not checked.
        const std::string p = path("gt_gap.csv");
        jsve::LogWriter w(p, good_meta(), returning(/*gt=*/true));
        jsve::Frame f = good_frame(1000, true);
        const jsve::Status s1 = w.write(f);
        f = good_frame(2000);
        f.has_gt = false;
        f.gt_q[0] = nan;
        const jsve::Status s2 = w.write(f);
        const jsve::Status c = w.close();
        report("frame_without_ground_truth",
               s1 == jsve::Status::kOk && s2 == jsve::Status::kOk && c == jsve::Status::kOk && exists(p), w.last_error());
    }
    {  // has_pose = false (outside states 2, 3, 5) leaves the ten vis_* fields empty, unchecked.
        const std::string p = path("no_pose.csv");
        jsve::LogWriter w(p, good_meta(), returning());
        const jsve::Status s1 = w.write(good_frame(1000, true));
        jsve::Frame f = good_frame(2000);
        f.state = 4;  // LOST
        f.has_pose = false;
        f.vis_p[0] = nan;
        f.vis_q[0] = 3.0;
        f.map_id = 8;  // a new map
        f.imu_init = false;
        f.imu_ba2 = false;
        const jsve::Status s2 = w.write(f);
        const jsve::Status c = w.close();
        report("frame_without_pose",
               s1 == jsve::Status::kOk && s2 == jsve::Status::kOk && c == jsve::Status::kOk && exists(p), w.last_error());
    }
    {  // A log with no frames is not a log: close() refuses to finalise it.
        const std::string p = path("no_frames.csv");
        jsve::LogWriter w(p, good_meta(), returning());
        const jsve::Status c = w.close();
        report("no_frames", c == jsve::Status::kNoFrames && exists(p + ".partial") && !exists(p), w.last_error());
    }
    {  // Without ground truth the gt_* fields are not written, so they are not checked either.
        const std::string p = path("gt_ignored.csv");
        jsve::LogWriter w(p, good_meta(), returning(false));
        jsve::Frame f = good_frame(1000, true);
        f.gt_p[0] = nan;
        const jsve::Status s = w.write(f);
        report("gt_fields_ignored_without_gt", s == jsve::Status::kOk && w.close() == jsve::Status::kOk && exists(p),
               w.last_error());
    }
    {  // Without world_frame the world_* fields are not written, so they are not checked either.
        const std::string p = path("world_ignored.csv");
        jsve::LogWriter w(p, good_meta(), returning(false, false));
        jsve::Frame f = good_frame(1000, true);
        f.world_s = -1.0;
        f.world_q[0] = nan;
        const jsve::Status s = w.write(f);
        report("world_fields_ignored_without_world_frame",
               s == jsve::Status::kOk && w.close() == jsve::Status::kOk && exists(p), w.last_error());
    }
    {  // world_frame: the eight columns last, after gt_*, on every frame (with or without a pose),
       // and camera_in_body in the metadata.
        const std::string p = path("world.csv");
        jsve::Metadata meta = good_meta();
        meta.set("camera_in_body", {0.5, 0.5, -0.5, 0.5, 0.1, -0.02, 0.003});
        jsve::LogWriter w(p, meta, returning(/*gt=*/true, /*world=*/true));
        const jsve::Status s1 = w.write(good_frame(1000, true));  // the identity
        jsve::Frame f = good_frame(2000);
        f.state = 4;
        f.has_pose = false;
        f.has_gt = false;
        f.world_q[0] = 0.0;
        f.world_q[1] = 1.0;
        f.world_t[0] = 1.5;
        f.world_t[1] = -2.0;
        f.world_t[2] = 0.25;
        f.world_s = 3.0;
        const jsve::Status s2 = w.write(f);
        const jsve::Status c = w.close();
        std::string text;
        if (std::FILE* in = std::fopen(p.c_str(), "rb")) {
            for (int ch; (ch = std::fgetc(in)) != EOF;) text += static_cast<char>(ch);
            std::fclose(in);
        }
        const bool header = text.find(",gt_qz,world_qw,world_qx,world_qy,world_qz,world_tx,world_ty,world_tz,world_s\n") !=
                            std::string::npos;
        const bool rows = text.find(",1.0,0.0,0.0,0.0,0.0,0.0,0.0,1.0\n") != std::string::npos &&
                          text.find(",,,,,,,0.0,1.0,0.0,0.0,1.5,-2.0,0.25,3.0\n") != std::string::npos;
        report("world_frame_columns",
               s1 == jsve::Status::kOk && s2 == jsve::Status::kOk && c == jsve::Status::kOk && header && rows,
               w.last_error() + " " + text.substr(text.find('\n') + 1));
    }
    {  // A quaternion off by less than the tolerance is accepted.
        const std::string p = path("near_unit.csv");
        jsve::LogWriter w(p, good_meta(), returning());
        jsve::Frame f = good_frame(1000, true);
        f.vis_q[0] = 1.0 + 5e-7;
        report("near_unit_quaternion_accepted", w.write(f) == jsve::Status::kOk && w.close() == jsve::Status::kOk,
               w.last_error());
    }
    {  // check() reports without failing the writer; the caller can repair the frame.
        const std::string p = path("repaired.csv");
        jsve::LogWriter w(p, good_meta(), returning());
        jsve::Frame f = good_frame(1000, true);
        f.vis_v[0] = nan;
        const jsve::Status c = w.check(f);
        f.vis_v[0] = 0.0;
        const jsve::Status s = w.write(f);
        const jsve::Status closed = w.close();
        report("check_does_not_fail_the_writer",
               c == jsve::Status::kNonFinite && s == jsve::Status::kOk && closed == jsve::Status::kOk && exists(p) &&
                   !exists(p + ".partial"),
               w.last_error());
    }
    {  // kThrow (the default) throws LogError carrying the Status and the column.
        const std::string p = path("thrown.csv");
        jsve::LogWriter w(p, good_meta());
        jsve::Frame f = good_frame(1000, true);
        f.vis_p[1] = nan;
        bool thrown = false;
        std::string what;
        try {
            w.write(f);
        } catch (const jsve::LogError& e) {
            thrown = e.status() == jsve::Status::kNonFinite;
            what = e.what();
        }
        bool close_threw = false;
        try {
            w.close();
        } catch (const jsve::LogError& e) {
            close_threw = e.status() == jsve::Status::kFailed;
        }
        report("throw_policy", thrown && what.find("vis_p[1]") != std::string::npos && close_threw &&
                                   exists(p + ".partial") && !exists(p),
               what);
    }
    {  // Metadata problems are reported by open(), before any file is created.
        struct Case {
            const char* name;
            jsve::Metadata meta;
        };
        jsve::Metadata no_run;
        no_run.set("sequence", "V1_01").set("fps", 20);
        jsve::Metadata fps_text;
        fps_text.set("sequence", "V1_01").set("run", 1).set("fps", "twenty");
        jsve::Metadata run_double;
        run_double.set("sequence", "V1_01").set("run", 1.5).set("fps", 20);
        jsve::Metadata nan_level = good_meta();
        nan_level.set("level", nan);
        jsve::Metadata bad_utf8 = good_meta();
        bad_utf8.set("frontend", "caf\xC3");
        jsve::Metadata size_scalar = good_meta();
        size_scalar.set("image_size", 752);
        jsve::Metadata size_doubles = good_meta();
        size_doubles.set("image_size", {752.0, 480.0});
        jsve::Metadata size_three = good_meta();
        size_three.set("image_size", {752, 480, 1});
        jsve::Metadata fps_zero = good_meta();
        fps_zero.set("fps", 0);
        jsve::Metadata gravity_two = good_meta();
        gravity_two.set("gravity", {0.0, -9.81});
        jsve::Metadata grid_other = good_meta();
        grid_other.set("grid", {8, 6});
        jsve::Metadata gt_source_int = good_meta();
        gt_source_int.set("gt_source", 3);
        jsve::Metadata big_unsigned = good_meta();
        big_unsigned.set("seed", std::numeric_limits<std::uint64_t>::max());
        jsve::Metadata rule_int = good_meta();
        rule_int.set("rule", 15);
        jsve::Metadata switch_model_list = good_meta();
        switch_model_list.set("switch_model", {1, 2});
        jsve::Metadata camera_scalar = good_meta();
        camera_scalar.set("camera_in_body", 1.0);
        jsve::Metadata camera_six = good_meta();
        camera_six.set("camera_in_body", {1.0, 0.0, 0.0, 0.0, 0.1, 0.2});
        jsve::Metadata camera_non_unit = good_meta();
        camera_non_unit.set("camera_in_body", {1.0, 0.1, 0.0, 0.0, 0.1, 0.2, 0.3});
        jsve::Metadata camera_huge = good_meta();
        camera_huge.set("camera_in_body", {1.0, 0.0, 0.0, 0.0, 1e39, 0.0, 0.0});
        const Case cases[] = {{"meta_missing_run", no_run},       {"meta_fps_string", fps_text},
                              {"meta_run_double", run_double},    {"meta_nan_double", nan_level},
                              {"meta_invalid_utf8", bad_utf8},    {"meta_image_size_scalar", size_scalar},
                              {"meta_image_size_doubles", size_doubles}, {"meta_image_size_three", size_three},
                              {"meta_fps_zero", fps_zero},        {"meta_gravity_two", gravity_two},
                              {"meta_grid_not_8x8", grid_other},  {"meta_gt_source_int", gt_source_int},
                              {"meta_unsigned_overflow", big_unsigned}, {"meta_rule_int", rule_int},
                              {"meta_switch_model_list", switch_model_list},
                              {"meta_camera_in_body_scalar", camera_scalar},
                              {"meta_camera_in_body_six", camera_six},
                              {"meta_camera_in_body_non_unit", camera_non_unit},
                              {"meta_camera_in_body_beyond_float32", camera_huge}};
        for (const Case& c : cases) {
            const std::string p = path(std::string(c.name) + ".csv");
            jsve::LogWriter w;
            const jsve::Status s = w.open(p, c.meta, returning());
            report(c.name, s == jsve::Status::kBadMetadata && !w.is_open() && !exists(p + ".partial"), w.last_error());
        }
    }
    {  // An existing log is never replaced silently; with overwrite it is removed at open.
        const std::string p = path("existing.csv");
        {
            jsve::LogWriter w(p, good_meta(), returning());
            w.write(good_frame(1000, true));
            w.close();
        }
        jsve::LogWriter refused;
        const jsve::Status s = refused.open(p, good_meta(), returning());
        report("exists_refused", s == jsve::Status::kExists && exists(p) && !exists(p + ".partial"), refused.last_error());
        jsve::Options o = returning();
        o.overwrite = true;
        jsve::LogWriter w(p, good_meta(), o);
        const bool removed_at_open = !exists(p) && exists(p + ".partial");
        w.write(good_frame(5000, true));
        const jsve::Status closed = w.close();
        report("overwrite_removes_old_log_at_open",
               removed_at_open && closed == jsve::Status::kOk && exists(p) && count_lines(p) == 4, w.last_error());
    }
    {  // Calls on a writer that is not open.
        jsve::LogWriter never_opened;  // default policy: throw
        bool thrown = false;
        try {
            never_opened.write(good_frame(1));
        } catch (const jsve::LogError& e) {
            thrown = e.status() == jsve::Status::kNotOpen;
        }
        const std::string p = path("twice.csv");
        jsve::LogWriter v(p, good_meta(), returning());
        const jsve::Status again = v.open(p, good_meta(), returning());
        v.write(good_frame(1000, true));
        const jsve::Status c1 = v.close();
        const jsve::Status c2 = v.close();
        const jsve::Status w2 = v.write(good_frame(1));
        report("not_open_and_already_open",
               thrown && again == jsve::Status::kAlreadyOpen && c1 == jsve::Status::kOk &&
                   c2 == jsve::Status::kNotOpen && w2 == jsve::Status::kNotOpen && exists(p));
    }
    {  // The destructor of an open writer abandons the log: only `.partial` remains.
        const std::string p = path("abandoned.csv");
        {
            jsve::LogWriter w(p, good_meta(), returning());
            w.write(good_frame(1000, true));
            w.write(good_frame(2000));
        }
        report("destructor_leaves_partial", exists(p + ".partial") && !exists(p) && count_lines(p + ".partial") == 4);
    }
    {  // A moved writer keeps writing the same log.
        const std::string p = path("moved.csv");
        jsve::LogWriter a(p, good_meta(), returning());
        a.write(good_frame(1000, true));
        jsve::LogWriter b(std::move(a));
        const jsve::Status s = b.write(good_frame(2000));
        const jsve::Status c = b.close();
        report("move", s == jsve::Status::kOk && c == jsve::Status::kOk && !a.is_open() && b.frames() == 2 &&
                           count_lines(p) == 5);
    }
    {  // flush_every: frames reach the file every N frames, not before (64 KiB stdio buffer).
        const std::string p = path("flush.csv");
        jsve::Options o = returning();
        o.flush_every = 2;
        jsve::LogWriter w(p, good_meta(), o);
        w.write(good_frame(1000, true));
        const int after1 = count_lines(p + ".partial");
        w.write(good_frame(2000));
        const int after2 = count_lines(p + ".partial");
        w.write(good_frame(3000));
        const int after3 = count_lines(p + ".partial");
        w.close();
        const int final_lines = count_lines(p);
        report("flush_every", after1 == 2 && after2 == 4 && after3 == 4 && final_lines == 6,
               std::to_string(after1) + " " + std::to_string(after2) + " " + std::to_string(after3) + " " +
                   std::to_string(final_lines));
    }
    {  // An I/O failure (missing directory) is an error, not a crash.
        jsve::LogWriter w;
        const jsve::Status s = w.open(path("no/such/dir/x.csv"), good_meta(), returning());
        report("io_error", s == jsve::Status::kIoError && !w.is_open(), w.last_error());
    }
    std::printf("failures %d\n", g_failures);
    return g_failures;
}
