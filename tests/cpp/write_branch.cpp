// A log continued in a forked child under another name (LogWriter::flush and continue_as), as a lockstep
// branch of the ORB-SLAM3 driver does; tests/test_log_v3.py reads both logs back.
//
// usage: write_branch PARENT.csv CHILD.csv   (paths of one length)
//   frames k = 0..2 (t_ns 1000 + k, n_inliers k) before the fork; then the parent writes k = 3, 4 and
//   the child k = 3..5 with n_inliers 100 + k. On stdout: "exists <status>" for a continue_as onto an
//   existing file without overwrite, "length <status>" onto a path of another length, and
//   "child <exit status>".
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "jsve_log.hpp"

static jsve::Frame frame(int k, int inliers) {
    jsve::Frame f;
    f.t_ns = 1000 + k;
    f.state = 2;
    f.n_extracted = 500;
    f.n_inliers = inliers;
    return f;
}

int main(int argc, char** argv) {
    if (argc != 3) return 2;
    jsve::Metadata meta;
    meta.set("sequence", "BR").set("run", 0).set("fps", 20);
    jsve::Options options;
    options.on_error = jsve::OnError::kReturn;
    jsve::LogWriter log(argv[1], meta, options);
    for (int k = 0; k < 3; ++k) log.write(frame(k, k));
    {
        std::FILE* taken = std::fopen((std::string(argv[2]) + ".taken").c_str(), "w");
        std::fclose(taken);
    }
    if (log.flush() != jsve::Status::kOk) return 1;
    const pid_t pid = fork();
    if (pid == 0) {
        jsve::LogWriter probe(std::string(argv[2]) + ".probe", meta, options);  // refusal on a copy
        probe.write(frame(0, 0));
        probe.flush();
        std::printf("exists %s\n", jsve::to_string(probe.continue_as(std::string(argv[2]) + ".taken")));
        probe.abandon();
        jsve::LogWriter other(std::string(argv[2]) + ".probe", meta, options);
        other.write(frame(0, 0));
        std::printf("length %s\n", jsve::to_string(other.continue_as(std::string(argv[2]) + ".longer")));
        other.abandon();
        if (log.continue_as(argv[2]) != jsve::Status::kOk) std::_Exit(3);
        for (int k = 3; k < 6; ++k) log.write(frame(k, 100 + k));
        std::fflush(stdout);
        std::_Exit(log.close() == jsve::Status::kOk ? 0 : 4);
    }
    int status = 0;
    waitpid(pid, &status, 0);
    std::printf("child %d\n", WIFEXITED(status) ? WEXITSTATUS(status) : -1);
    for (int k = 3; k < 5; ++k) log.write(frame(k, k));
    return log.close() == jsve::Status::kOk ? 0 : 1;
}
