// jsve's lockstep gates for ORB-SLAM3 v1.0: Tracking, LocalMapping and LoopClosing take turns, so that
// a run depends only on its inputs and its seed (docs/frontend.md, "Lockstep runs").
//
// ORB-SLAM3 runs its three threads concurrently and lets them read each other's state: whether
// LocalMapping accepts keyframes (Tracking::NeedNewKeyFrame), whether a local BA is aborted
// (mbAbortBA), when a loop is corrected relative to the frames being tracked. Lockstep replaces this
// interleaving by one fixed order per frame:
//   1. Tracking processes the frame (System::TrackMonocular) while LocalMapping and LoopClosing are
//      parked at the top of their Run() loops (accepting keyframes, queues empty);
//   2. `settle` grants LocalMapping turns until its queue is empty, then LoopClosing turns until its
//      queue is empty, then waits for a global BA it started; each thread runs alone.
// The gates are anchored insertions (jsve/frontend/_build.py): a park at the top of LocalMapping::Run's
// and LoopClosing::Run's loops (their sleep at the loop's end is skipped), and a wait at the start of
// the global BA's thread until both workers are parked; ORB-SLAM3's own logic is unchanged. A parked
// thread still serves the requests ORB-SLAM3 makes of it and busy-waits for (a stop requested by
// LoopClosing or the global BA, a reset requested by Tracking, the finish requested by
// System::Shutdown): it leaves the park for one loop iteration, which is where ORB-SLAM3 serves them.
// Only one thread allocates at a time, so the heap's addresses, by which ORB-SLAM3 orders keyframes
// and map points, are the same in every repeat.
//
// Without `enable` the parks return at once: a stock or paced run is untouched.
//
// Exact branches: with every thread parked between two frames, `fork_parked` forks the process; the
// child continues the same run under another rule (or the same one, which then writes the parent's
// log byte for byte), on copies of the maps. Both processes finish their LocalMapping and LoopClosing
// threads before the fork and start them again after it, so that they take the same steps.
#pragma once

#include <pthread.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstdlib>
#include <mutex>
#include <new>
#include <thread>
#include <type_traits>

namespace jsve_hook {

enum Worker { kLocalMapping = 0, kLoopClosing = 1 };

// The turn-taking state shared by the tracker (the driver's thread) and the two workers.
struct Lockstep {
    std::atomic<bool> on{false};
    double timeout_s = 60.0;  // how long `settle` waits for a worker (s) before it gives up
    std::mutex m;
    std::condition_variable cv;
    std::uint64_t granted[2] = {0, 0};  // turns given to each worker
    std::uint64_t served[2] = {0, 0};   // turns each worker has finished (it parked after them)
    bool parked[2] = {false, false};
    bool queue_empty[2] = {true, true};  // the worker's keyframe queue when it last parked
    // Time accounting (s): each worker's time out of its park, the tracker's time in `settle`.
    double busy_s[2] = {0.0, 0.0};
    double settle_s = 0.0, gba_wait_s = 0.0;
    std::chrono::steady_clock::time_point left[2];
    // Each worker as its park records it, for `fork_parked`: its thread, the object, and a function that
    // clears the flags ORB-SLAM3's finish leaves set (so that Run() can start again).
    pthread_t thread[2] = {};
    void* worker[2] = {nullptr, nullptr};
    void (*revive[2])(void*) = {nullptr, nullptr};
    // LoopClosing's global-BA thread (LoopClosing::mpThreadGBA, published at its park). ORB-SLAM3
    // clears its running flag before the thread exits; `settle` joins it, so that its exit (which
    // frees memory) never overlaps the next frame.
    std::thread* gba_thread = nullptr;
};

// The process's lockstep state (defined in Tracking.cc's translation unit).
Lockstep& lockstep();

// Turns the parks on (before System starts its threads); `timeout_s` bounds each wait of `settle`.
void enable_lockstep(double timeout_s);

// Right after `settle_frame`, with every thread parked: fork()s the run. LocalMapping and LoopClosing
// finish before the fork and start again after it in both processes (threads on cached stacks, which
// allocate nothing), so that the child, which continues the run from the next frame, and the parent
// take the same steps; the time accounting restarts at zero. Returns fork()'s value (0 in the child,
// the child's pid in the parent), or -1 when lockstep is off, a worker is not parked or fork fails.
int fork_parked();

// The driver calls this after each System::TrackMonocular: LocalMapping, then LoopClosing, each alone
// until its queue is empty, then any global BA to its end, and both workers parked again. False when
// a wait ran past the timeout (the run is no longer in lockstep; the driver records that and stops).
// True at once when lockstep is off.
bool settle_frame();

// Called by a worker at the top of its Run() loop. `requested()`: ORB-SLAM3 asks something of this
// worker (stop, reset, finish); `queue_empty()`: its keyframe queue is empty. Returns when the worker
// has a turn or a request to serve; at once when lockstep is off. A worker thus never runs an
// iteration of its own accord, not even its first one while System is still being constructed.
template <class Requested, class QueueEmpty>
void park(Worker who, Requested&& requested, QueueEmpty&& queue_empty, void* self, void (*revive)(void*),
          std::thread* gba_thread = nullptr) {
    Lockstep& L = lockstep();
    if (!L.on.load(std::memory_order_acquire)) return;
    std::unique_lock<std::mutex> lock(L.m);
    const bool empty = queue_empty();
    if (gba_thread != nullptr) L.gba_thread = gba_thread;
    L.thread[who] = pthread_self();
    L.worker[who] = self;
    L.revive[who] = revive;
    const auto now = std::chrono::steady_clock::now();
    if (L.left[who].time_since_epoch().count() != 0)
        L.busy_s[who] += std::chrono::duration<double>(now - L.left[who]).count();
    L.served[who] = L.granted[who];
    L.parked[who] = true;
    L.queue_empty[who] = empty;
    L.cv.notify_all();
    // ORB-SLAM3 sets its request flags without notifying this condition variable: poll them.
    while (L.granted[who] == L.served[who] && !requested()) L.cv.wait_for(lock, std::chrono::milliseconds(1));
    L.parked[who] = false;
    L.left[who] = std::chrono::steady_clock::now();
}

// True in a lockstep run.
inline bool lockstep_on() { return lockstep().on.load(std::memory_order_acquire); }

// At the end of a worker's Run() loop, before its sleep: in lockstep the loop goes on to its park.
#define JSVE_LOCKSTEP_SKIP_SLEEP() \
    if (::jsve_hook::lockstep_on()) continue

// At the start of LoopClosing::RunGlobalBundleAdjustment: in lockstep the global BA starts once both
// workers are parked (LoopClosing launches it and goes on with its own iteration), so that it runs alone.
inline void wait_workers_parked() {
    Lockstep& L = lockstep();
    if (!L.on.load(std::memory_order_acquire)) return;
    std::unique_lock<std::mutex> lock(L.m);
    while (!(L.parked[kLocalMapping] && L.parked[kLoopClosing])) L.cv.wait_for(lock, std::chrono::milliseconds(1));
}

// At the top of LocalMapping::Run's loop (its protected members are visible there, and to a lambda
// defined there: `revive` clears what LocalMapping::SetFinish leaves set).
#define JSVE_LOCKSTEP_PARK_LOCAL_MAPPING()                                                           \
    do {                                                                                             \
        using jsve_self_t = std::remove_pointer_t<decltype(this)>;                                   \
        ::jsve_hook::park(                                                                           \
            ::jsve_hook::kLocalMapping,                                                              \
            [this] {                                                                                 \
                bool reset;                                                                          \
                {                                                                                    \
                    std::unique_lock<std::mutex> lock_(mMutexReset);                                 \
                    reset = mbResetRequested || mbResetRequestedActiveMap;                           \
                }                                                                                    \
                return reset || CheckFinish() || (stopRequested() && !isStopped());                  \
            },                                                                                       \
            [this] { return KeyframesInQueue() == 0; }, this, +[](void* self_) {                     \
                jsve_self_t* w_ = static_cast<jsve_self_t*>(self_);                                  \
                std::unique_lock<std::mutex> finish_(w_->mMutexFinish);                              \
                std::unique_lock<std::mutex> stop_(w_->mMutexStop);                                  \
                w_->mbFinishRequested = w_->mbFinished = w_->mbStopped = false;                      \
            });                                                                                      \
    } while (0)

// At the top of LoopClosing::Run's loop.
#define JSVE_LOCKSTEP_PARK_LOOP_CLOSING()                                                            \
    do {                                                                                             \
        using jsve_self_t = std::remove_pointer_t<decltype(this)>;                                   \
        ::jsve_hook::park(                                                                           \
            ::jsve_hook::kLoopClosing,                                                               \
            [this] {                                                                                 \
                bool reset;                                                                          \
                {                                                                                    \
                    std::unique_lock<std::mutex> lock_(mMutexReset);                                 \
                    reset = mbResetRequested || mbResetActiveMapRequested;                           \
                }                                                                                    \
                return reset || CheckFinish();                                                       \
            },                                                                                       \
            [this] { return !CheckNewKeyFrames(); }, this,                                           \
            +[](void* self_) {                                                                       \
                jsve_self_t* w_ = static_cast<jsve_self_t*>(self_);                                  \
                std::unique_lock<std::mutex> finish_(w_->mMutexFinish);                              \
                w_->mbFinishRequested = w_->mbFinished = false;                                      \
            },                                                                                       \
            mpThreadGBA);                                                                            \
    } while (0)

}  // namespace jsve_hook

#ifdef JSVE_HOOK_IMPLEMENTATION

namespace jsve_hook {

Lockstep& lockstep() {
    static Lockstep L;
    return L;
}

void enable_lockstep(double timeout_s) {
    lockstep().timeout_s = timeout_s;
    lockstep().on.store(true, std::memory_order_release);
}

namespace detail {

template <class Done>
bool wait_until(Lockstep& L, std::unique_lock<std::mutex>& lock, Done&& done,
                std::chrono::steady_clock::time_point deadline) {
    while (!done()) {
        if (L.cv.wait_until(lock, std::min(deadline, std::chrono::steady_clock::now() + std::chrono::milliseconds(1))) ==
                std::cv_status::timeout &&
            std::chrono::steady_clock::now() >= deadline)
            return done();
    }
    return true;
}

// One turn of `who`: wait until it is parked, grant it a turn, wait until it has parked again.
inline bool turn(Lockstep& L, Worker who, std::chrono::steady_clock::time_point deadline) {
    std::unique_lock<std::mutex> lock(L.m);
    if (!wait_until(L, lock, [&] { return L.parked[who]; }, deadline)) return false;
    const std::uint64_t mine = ++L.granted[who];
    L.cv.notify_all();
    return wait_until(L, lock, [&] { return L.served[who] >= mine && L.parked[who]; }, deadline);
}

}  // namespace detail

namespace detail {

template <class Worker>
void* run_worker(void* worker) {
    static_cast<Worker*>(worker)->Run();
    return nullptr;
}

// A detached thread running `worker->Run()`, made with pthread_create: std::thread would allocate its
// state on the heap, and the child's heap must stay the parent's.
template <class Worker>
bool start_worker(Worker* worker) {
    pthread_t thread;
    if (pthread_create(&thread, nullptr, &run_worker<Worker>, worker) != 0) return false;
    pthread_detach(thread);
    return true;
}

}  // namespace detail

// fork_parked's work, given the run's LocalMapping and LoopClosing (the hook's TrackerView knows them).
// Both processes end up alike: the workers finish (ORB-SLAM3's own finish request, one after the other,
// each joined), their flags are cleared, the process forks with the tracker as its only thread, and
// each side starts the workers again on stacks glibc has cached and waits until they park. The parent
// thus takes the same steps as its child, which is what makes a branch under the parent's rule equal
// the parent's log; both differ from a run without the branch, whose workers live on.
template <class LocalMappingT, class LoopClosingT>
int fork_parked(LocalMappingT* local_mapping, LoopClosingT* loop_closing) {
    Lockstep& L = lockstep();
    if (!L.on.load() || local_mapping == nullptr || loop_closing == nullptr) return -1;
    {
        std::unique_lock<std::mutex> lock(L.m);
        if (!L.parked[kLocalMapping] || !L.parked[kLoopClosing]) return -1;
    }
    auto retire = [&](Worker who, auto* worker) {
        worker->RequestFinish();
        pthread_join(L.thread[who], nullptr);
        L.revive[who](L.worker[who]);
        L.parked[who] = false;
    };
    retire(kLocalMapping, local_mapping);
    retire(kLoopClosing, loop_closing);
    const pid_t pid = fork();
    if (pid < 0) return pid;
    for (int w = 0; w < 2; ++w) {
        L.granted[w] = L.served[w] = 0;
        L.queue_empty[w] = true;
        L.busy_s[w] = 0.0;
        L.left[w] = std::chrono::steady_clock::time_point();
    }
    L.settle_s = L.gba_wait_s = 0.0;
    if (!detail::start_worker(local_mapping) || !detail::start_worker(loop_closing)) std::_Exit(4);
    std::unique_lock<std::mutex> lock(L.m);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    if (!detail::wait_until(L, lock, [&] { return L.parked[kLocalMapping] && L.parked[kLoopClosing]; }, deadline))
        return -1;
    return pid;
}

// settle_frame's work, given the run's LoopClosing (the hook's TrackerView knows it).
template <class LoopClosingT>
bool settle(LoopClosingT* loop_closing) {
    Lockstep& L = lockstep();
    if (!L.on.load()) return true;
    const auto start = std::chrono::steady_clock::now();
    const auto deadline = start + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                      std::chrono::duration<double>(L.timeout_s));
    bool ok = true;
    for (int round = 0; ok; ++round) {
        ok = detail::turn(L, kLocalMapping, deadline) && detail::turn(L, kLoopClosing, deadline);
        if (!ok) break;
        const auto gba = std::chrono::steady_clock::now();
        while (loop_closing->isRunningGBA() && std::chrono::steady_clock::now() < deadline)
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
        ok = !loop_closing->isRunningGBA();
        std::thread* gba_thread = nullptr;
        {
            std::unique_lock<std::mutex> lock(L.m);
            std::swap(gba_thread, L.gba_thread);
        }
        if (ok && gba_thread != nullptr && gba_thread->joinable()) gba_thread->join();
        L.gba_wait_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - gba).count();
        std::unique_lock<std::mutex> lock(L.m);
        ok = ok && detail::wait_until(L, lock, [&] { return L.parked[kLocalMapping] && L.parked[kLoopClosing]; },
                                      deadline);
        if (ok && L.queue_empty[kLocalMapping] && L.queue_empty[kLoopClosing]) break;
    }
    L.settle_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return ok;
}

}  // namespace jsve_hook

#endif  // JSVE_HOOK_IMPLEMENTATION
