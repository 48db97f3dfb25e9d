// Algorithm 1 as the ORB-SLAM3 hook runs it (jsve_keypoints.hpp, jsve_orbslam3_hook.hpp without
// ORB-SLAM3); tests/test_frontend_keypoints.py compares it with jsve.masks.dynamic_keypoints.
//
// stdin: `W H w h`, then H rows of W obj_ids (the instance map of a W x H image), then `N` and N lines
// `x y` (C99 hex floats, exact): keypoints of that image resized to w x h, as ORB-SLAM3 extracts them.
// stdout: one line per keypoint, `D X Y`: D 1 when on a dynamic object, X Y its coordinates in the
// mask's image (jsve::source_coordinate, hex floats); then `kept I...`, the keypoints
// drop_dynamic_keypoints keeps (by index), and `aligned 1` when every kept keypoint still goes with
// its own descriptor row.
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "jsve_orbslam3_hook.hpp"

namespace {

struct Point { float x = 0.0f, y = 0.0f; };
struct KeyPoint { Point pt; int id = 0; };  // cv::KeyPoint's pt, and which keypoint it was

// The part of cv::Mat that drop_dynamic_keypoints uses: rows of `cols` bytes, and a view of some rows.
struct Rows {
    std::shared_ptr<std::vector<unsigned char>> data;
    int rows = 0, cols = 0, first = 0;
    unsigned char* ptr(int r) { return data->data() + static_cast<std::size_t>(first + r) * static_cast<std::size_t>(cols); }
    std::size_t elemSize() const { return 1; }
    Rows rowRange(int begin, int end) const {
        Rows view = *this;
        view.first = first + begin;
        view.rows = end - begin;
        return view;
    }
};

}  // namespace

int main() {
    int width = 0, height = 0, resized_width = 0, resized_height = 0;
    std::cin >> width >> height >> resized_width >> resized_height;
    std::vector<std::uint16_t> pixels(static_cast<std::size_t>(width) * static_cast<std::size_t>(height));
    for (std::uint16_t& p : pixels) std::cin >> p;
    const jsve::InstanceMask mask{pixels.data(), width, height, width};
    int n = 0;
    std::cin >> n;
    std::vector<KeyPoint> keys(static_cast<std::size_t>(n));
    Rows descriptors{std::make_shared<std::vector<unsigned char>>(static_cast<std::size_t>(n) * 32), n, 32, 0};
    for (int i = 0; i < n; ++i) {
        std::string x, y;
        std::cin >> x >> y;
        KeyPoint& k = keys[static_cast<std::size_t>(i)];
        k.pt.x = std::strtof(x.c_str(), nullptr), k.pt.y = std::strtof(y.c_str(), nullptr), k.id = i;
        const float sx = jsve::source_coordinate(k.pt.x, width, resized_width);
        const float sy = jsve::source_coordinate(k.pt.y, height, resized_height);
        const bool dynamic = jsve::on_dynamic_object(mask, static_cast<double>(sx), static_cast<double>(sy));
        std::printf("%d %a %a\n", dynamic ? 1 : 0, static_cast<double>(sx), static_cast<double>(sy));
        for (int b = 0; b < 32; ++b) descriptors.ptr(i)[b] = static_cast<unsigned char>((i * 7 + b) % 256);
    }
    jsve_hook::drop_dynamic_keypoints(mask, keys, descriptors, resized_width, resized_height);
    std::printf("kept");
    bool aligned = descriptors.rows == static_cast<int>(keys.size());
    for (std::size_t k = 0; k < keys.size(); ++k) {
        std::printf(" %d", keys[k].id);
        for (int b = 0; b < 32; ++b)
            aligned = aligned && descriptors.ptr(static_cast<int>(k))[b] == static_cast<unsigned char>((keys[k].id * 7 + b) % 256);
    }
    std::printf("\naligned %d\n", aligned ? 1 : 0);
    return 0;
}
