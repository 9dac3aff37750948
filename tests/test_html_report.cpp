// report.html (src/eval/html_report.hpp): one self-contained page, names escaped, and in headless
// Chromium its script runs (sorting, the comparison's pictures) and it renders.
#include "catch_torch.hpp"

#include <fstream>
#include <regex>

#include "core/util.hpp"
#include "eval/html_report.hpp"
#include "helpers.hpp"
#include "io/image.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;

namespace {

size_t count(const std::string& text, const std::string& what) {
  size_t n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// A set of `images` scenes with a truth and two methods (one with a hostile name) on disk.
HtmlSet make_set(const std::filesystem::path& dir, int images) {
  HtmlSet set;
  set.name = "held out";
  set.caption = "three scenes <made up>";
  set.methods = {"good", "<b>bad & \"odd\"</b>"};
  set.gt_dir = dir / "gt", set.rec_dir = dir / "rec";
  std::filesystem::create_directories(set.gt_dir);
  for (const auto& m : set.methods) std::filesystem::create_directories(set.rec_dir / m);
  torch::manual_seed(4);
  for (int i = 0; i < images; ++i) {
    const auto name = "scene" + std::to_string(i) + ".png";
    const auto truth = torch::rand({3, 32, 32});
    write_rgb8(set.gt_dir / name, truth);
    for (size_t k = 0; k < set.methods.size(); ++k) {
      write_rgb8(set.rec_dir / set.methods[k] / name, (truth * (0.5 + 0.2 * k)).clamp(0, 1));
      set.images.push_back({name, set.methods[k], 20.0 + i + k, 0.5 + 0.01 * i});
    }
  }
  for (const auto& m : set.methods) {
    MethodScore s{m};
    s.count = images, s.psnr = 21, s.ssim = 0.6;
    set.scores.push_back(s);
    set.ms_per_image.push_back(12.5);
  }
  set.gallery = 2;
  return set;
}

}  // namespace

TEST_CASE("report.html is one self-contained page with escaped names", "[report][html]") {
  test::Scratch s("html");
  const auto set = make_set(s.dir, 3);
  const auto page = html_report("Report <1>", "made by a test & nothing else", {set});
  CHECK(page.rfind("<!DOCTYPE html>", 0) == 0);
  // Nothing is fetched: no URL anywhere, a policy that forbids it, images inline.
  CHECK(page.find("http:") == std::string::npos);
  CHECK(page.find("https:") == std::string::npos);
  CHECK(page.find("<link") == std::string::npos);
  CHECK(page.find("@import") == std::string::npos);
  CHECK_THAT(page, Contains("default-src 'none'"));
  // The gallery: 2 scenes (its limit) x (truth + 2 methods), each picture embedded once.
  CHECK(count(page, "src=\"data:image/jpeg;base64,") == 6);
  // Names reach the page only escaped.
  CHECK(page.find("<b>bad") == std::string::npos);
  CHECK_THAT(page, Contains("&lt;b&gt;bad &amp; &quot;odd&quot;&lt;/b&gt;") && Contains("Report &lt;1&gt;") &&
                       Contains("three scenes &lt;made up&gt;"));
  // Sortable tables: the methods' and every image's (all 3 scenes, with their scores as sort keys).
  CHECK(count(page, "class=\"sortable\"") == 2);
  CHECK_THAT(page, Contains("<td>scene2.png</td><td data-v=\"22\">22.00</td>"));
  CHECK_THAT(page, Contains("class=\"compare\"") && Contains("type=\"range\""));
}

TEST_CASE("report.html in headless Chromium: its script runs and the page renders", "[report][chromium][solo]") {
  const auto which = test::run_shell("command -v chromium || command -v chromium-browser");
  if (which.code != 0) SKIP_TEST("no chromium (Debian package chromium; scripts/setup.sh installs it)");
  const std::string chromium = which.output.substr(0, which.output.find('\n'));
  test::Scratch s("html_chromium");
  write_text_atomically(s.dir / "report.html", html_report("Report", "test", {make_set(s.dir, 3)}));
  // --no-sandbox: the tests may run as root; no network is needed (the page asks for none).
  const std::string base = q(chromium) +
                           " --headless --no-sandbox --disable-gpu --no-first-run --disable-extensions "
                           "--user-data-dir=" +
                           q(s.dir / "profile") + " ";
  const auto url = "file://" + (s.dir / "report.html").string();
  auto r = test::run_shell(base + "--virtual-time-budget=5000 --dump-dom " + q(url));
  INFO(r.output.substr(0, 2000));
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("data-ready=\"yes\""));  // the script ran to its end
  // The comparison took its two pictures from the gallery: the truth on the left, the last method on the right.
  CHECK(std::regex_search(r.output, std::regex("<img class=\"right\" alt=\"right\" src=\"data:image/jpeg")));
  CHECK(std::regex_search(r.output, std::regex("<img class=\"left\" alt=\"left\" src=\"data:image/jpeg")));
  r = test::run_shell(base + "--window-size=1000,1200 --screenshot=" + q(s.dir / "shot.png") + " " + q(url));
  INFO(r.output.substr(0, 2000));
  REQUIRE(std::filesystem::exists(s.dir / "shot.png"));
  const auto shot = read_rgb(s.dir / "shot.png");
  CHECK(shot.size(2) == 1000);
  CHECK(shot.std().item<double>() > 0.05);  // tables and pictures, not a blank page
}
