// The hook's rule in the loop (jsve_orbslam3_hook.hpp without ORB-SLAM3): reads one case per line,
//   KIND INPUTS W_A U_B P Q RHO N_FEATURES IMU_INIT NOT_INIT RELOC RECOVERY
//   N_EXTRACTED N_INLIERS N_FRUSTUM BIN_0 .. BIN_63 IN_RELOC RECENTLY_LOST IMU_OK STEREO
// (KIND 0 inliers / 1 SVE; INPUTS 0 jsve / 1 authors-eq1 / 2 authors-option1) and prints the score
// (17 significant digits) and the success test (0 / 1); tests/test_hook_rule.py compares both with jsve.
#include <cstdio>
#include <iostream>

#include "jsve_orbslam3_hook.hpp"

int main() {
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
