// Compiled by tests/test_frontend.py with strict warning flags: the header included twice (include
// guard) and every template of its interface instantiated, so that warnings in any of them show.

#include "jsve_log.hpp"
#include "jsve_log.hpp"

#include <cstddef>
#include <cstdint>
#include <vector>

int use_every_template() {
    jsve::Metadata m;
    const std::vector<int> ints = {1, 2};
    const std::vector<double> doubles = {0.5, 1.5};
    const std::vector<std::int64_t> longs = {std::int64_t{1} << 40};
    const float floats[2] = {1.0f, 2.0f};
    m.set("sequence", "s").set("name", std::string("n")).set("run", 1).set("fps", 20.0);
    m.set("a", 1L).set("b", 2LL).set("c", 3U).set("d", std::uint64_t{4}).set("e", short{5}).set("f", 0.5f);
    m.set("g", {1, 2}).set("h", {0.5, 1.5}).set("i", ints).set("j", doubles).set("k", longs);
    m.set_array("l", floats, 2).set_array("m", ints.data(), ints.size());
    jsve::Frame f;
    static std::vector<std::size_t> grid[jsve::kGridCols][jsve::kGridRows];
    jsve::fill_bins_from_grid(f, [](int c, int r) { return grid[c][r].size(); });
    jsve::fill_bins_from_grid(f, [](int c, int r) { return c + r; });
    jsve::Options o;
    o.on_error = jsve::OnError::kReturn;
    jsve::LogWriter w;
    std::string why;
    const jsve::Status s = w.check(f, &why);
    jsve::LogWriter moved(std::move(w));
    return static_cast<int>(s) + static_cast<int>(m.to_json().size()) + (moved.is_open() ? 1 : 0) +
           jsve::bin_of_cell(63, 47) + static_cast<int>(jsve::to_string(s)[0]);
}
