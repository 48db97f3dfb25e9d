// The hook's rule in the loop (jsve_orbslam3_hook.hpp without ORB-SLAM3): reads one case per line,
//   KIND INPUTS W_A U_B P Q RHO N_FEATURES IMU_INIT NOT_INIT RELOC RECOVERY
//   N_EXTRACTED N_INLIERS N_FRUSTUM BIN_0 .. BIN_63 IN_RELOC RECENTLY_LOST IMU_OK STEREO
// (KIND 0 inliers / 1 SVE; INPUTS 0 jsve / 1 authors-eq1 / 2 authors-option1) and prints the score
// (17 significant digits) and the success test (0 / 1); tests/test_hook_rule.py compares both with jsve.
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>

#include "jsve_orbslam3_hook.hpp"

// `hook_rule --parse FLAG TEXT`: the driver's rule option through jsve_hook::parse_rule; prints the rule
// (kind inputs w_a u_b p q rho imu_init not_init reloc recovery) or the error, exit 1.
int parse(const std::string& flag, const std::string& text) {
    jsve_hook::Rule r;
    std::string error;
    if (!jsve_hook::parse_rule(flag, text, &r, &error)) {
        std::printf("error: %s\n", error.c_str());
        return 1;
    }
    std::printf("%d %d %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g\n", r.kind == jsve_hook::ScoreKind::kSve,
                static_cast<int>(r.inputs), r.w_a, r.u_b, r.p, r.q, r.rho, r.imu_init, r.not_init, r.reloc, r.recovery);
    return 0;
}

// The hook's state, which ORB-SLAM3's Tracking.cc defines in the real build.
jsve_hook::HookState& jsve_hook::state() {
    static HookState s;
    return s;
}

// `hook_rule --cleared STEPS`: STEPS a string of f (a frame begins, as Tracking::GrabImageMonocular
// begins it), r (ResetActiveMap), a (Reset), n (CreateMapInAtlas), l (a loop closure); prints per frame
// whether it was constructed after ORB-SLAM3 cleared its last frame (1: its preintegration is not logged).
int cleared(const std::string& steps) {
    const std::vector<int> mlRelativeFramePoses;  // what JSVE_HOOK_BEGIN_FRAME reads of Tracking
    for (char step : steps) {
        if (step == 'f') {
            JSVE_HOOK_BEGIN_FRAME();
            std::printf("%d", jsve_hook::state().previous_frame_cleared ? 1 : 0);
        } else if (step == 'r') {
            JSVE_HOOK_EVENT(kEventReset);
        } else if (step == 'a') {
            JSVE_HOOK_EVENT(kEventResetAll);
        } else if (step == 'n') {
            JSVE_HOOK_EVENT(kEventNewMap);
        } else if (step == 'l') {
            JSVE_HOOK_EVENT(kEventLoop);
        }
    }
    std::printf("\n");
    return 0;
}

int main(int argc, char** argv) {
    if (argc == 4 && std::string(argv[1]) == "--parse") return parse(argv[2], argv[3]);
    if (argc == 3 && std::string(argv[1]) == "--cleared") return cleared(argv[2]);
    // `hook_rule --stamp NAME SECONDS`: the stamp the hook logs for an image of that name (jsve_hook::stamp_ns).
    if (argc == 4 && std::string(argv[1]) == "--stamp") {
        std::printf("%lld\n", static_cast<long long>(jsve_hook::stamp_ns(argv[2], std::stod(argv[3]))));
        return 0;
    }
    int kind = 0, inputs = 0;
    while (std::cin >> kind >> inputs) {
        jsve_hook::Rule r;
        jsve_hook::FrameCounts c;
        r.kind = kind == 0 ? jsve_hook::ScoreKind::kInliers : jsve_hook::ScoreKind::kSve;
        r.inputs = inputs == 0 ? jsve_hook::SveInputs::kJsve
                               : (inputs == 1 ? jsve_hook::SveInputs::kAuthorsEq1 : jsve_hook::SveInputs::kAuthorsOption1);
        std::cin >> r.w_a >> r.u_b >> r.p >> r.q >> r.rho >> r.n_features >> r.imu_init >> r.not_init >> r.reloc >>
            r.recovery >> c.n_extracted >> c.n_inliers >> c.n_frustum;
        for (int& b : c.bins) std::cin >> b;
        int in_reloc = 0, recently_lost = 0, imu_ok = 0, stereo = 0;
        std::cin >> in_reloc >> recently_lost >> imu_ok >> stereo;
        const double score = jsve_hook::rule_score(r, c);
        const bool ok = jsve_hook::rule_succeeds(r, score, in_reloc != 0, recently_lost != 0, imu_ok != 0, stereo != 0);
        std::printf("%.17g %d\n", score, ok ? 1 : 0);
    }
    return 0;
}
