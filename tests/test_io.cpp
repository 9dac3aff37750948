// io/: .mat files, raw captures, images, dataset lists.
#include "catch_torch.hpp"

#include <matio.h>
#include <set>
#include <sstream>
#include <tuple>
#include <fstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include <numeric>

#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/dataset.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/raw.hpp"

#include <opencv2/imgcodecs.hpp>
#include <zlib.h>

using namespace flatnet;
using Catch::Matchers::Contains;

TEST_CASE(".mat round trip keeps MATLAB's indexing (column-major)", "[io][mat]") {
  test::Scratch s("mat");
  auto a = torch::arange(6, torch::kFloat64).reshape({2, 3});
  auto c = torch::arange(24, torch::kFloat64).reshape({2, 3, 4});
  write_mat(s.dir / "x.mat", {{"a", a}, {"c", c}});
  MatReader m(s.dir / "x.mat");
  CHECK(torch::equal(m.read("a"), a));
  CHECK(torch::equal(m.read("c"), c));
  CHECK(m.has("a"));
  CHECK_FALSE(m.has("zz"));
}

TEST_CASE(".mat v7.3 round trip when matio supports HDF5", "[io][mat][solo]") {
  test::Scratch s("mat73");
  auto a = torch::rand({5, 7}, torch::kFloat64);
  try {
    write_mat(s.dir / "x.mat", {{"a", a}}, MatVersion::v73);
  } catch (const Error& e) {
    SKIP_TEST(std::string("v7.3 unsupported by this matio: ") + e.what());
  }
  CHECK(torch::equal(MatReader(s.dir / "x.mat").read("a"), a));
}

TEST_CASE(".mat: every numeric class reads as its values, v5 and v7.3 (the isolated reader)", "[io][mat][solo]") {
  test::Scratch s("mat_classes");
  double d[2] = {0.1, 9};
  float f[2] = {1.5f, -2.25f};
  int8_t i8[2] = {-3, 4};
  uint8_t u8[2] = {200, 5};
  int16_t i16[2] = {-300, 7};
  int32_t i32[2] = {70000, -1};
  int64_t i64[2] = {int64_t{1} << 40, 3};
  const std::vector<std::tuple<const char*, matio_classes, matio_types, void*, std::vector<double>>> vars = {
      {"d", MAT_C_DOUBLE, MAT_T_DOUBLE, d, {0.1, 9}},
      {"f", MAT_C_SINGLE, MAT_T_SINGLE, f, {1.5, -2.25}},
      {"i8", MAT_C_INT8, MAT_T_INT8, i8, {-3, 4}},
      {"u8", MAT_C_UINT8, MAT_T_UINT8, u8, {200, 5}},
      {"i16", MAT_C_INT16, MAT_T_INT16, i16, {-300, 7}},
      {"i32", MAT_C_INT32, MAT_T_INT32, i32, {70000, -1}},
      {"i64", MAT_C_INT64, MAT_T_INT64, i64, {1099511627776.0, 3}}};
  for (const auto version : {MAT_FT_MAT5, MAT_FT_MAT73}) {
    const auto path = s.dir / (version == MAT_FT_MAT5 ? "v5.mat" : "v73.mat");
    mat_t* m = Mat_CreateVer(path.c_str(), nullptr, version);
    if (m == nullptr && version == MAT_FT_MAT73) SKIP_TEST("v7.3 unsupported by this matio");
    REQUIRE(m != nullptr);
    for (const auto& [name, cls, type, data, values] : vars) {
      size_t dims[2] = {1, 2};
      matvar_t* v = Mat_VarCreate(name, cls, type, 2, dims, data, 0);
      REQUIRE(Mat_VarWrite(m, v, MAT_COMPRESSION_NONE) == 0);
      Mat_VarFree(v);
    }
    Mat_Close(m);
    MatReader r(path);
    for (const auto& [name, cls, type, data, values] : vars) {
      INFO(path.filename().string() << " " << name);
      const auto t = r.read(name);
      CHECK(t.sizes() == torch::IntArrayRef({1, 2}));
      CHECK(t.scalar_type() == torch::kFloat64);
      CHECK(t[0][0].item<double>() == Approx(values[0]));
      CHECK(t[0][1].item<double>() == Approx(values[1]));
    }
  }
}

TEST_CASE("reading the reference calibration matches its known layout", "[io][mat]") {
  MatReader m(test::calib_path());
  auto p = m.read("P1b", {500, 256});
  // First entries as scipy.io.loadmat gives them (row-major view of MATLAB's P1b(1,1:4)).
  CHECK(p[0][0].item<double>() == Approx(-0.00464343).epsilon(1e-5));
}

TEST_CASE(".mat errors name the file and the problem", "[io][mat][errors]") {
  MatReader m(test::calib_path());
  REQUIRE_THROWS_WITH(m.read("P1x"), Contains("calib.mat") && Contains("missing variable 'P1x'"));
  REQUIRE_THROWS_WITH(m.read("P1b", {620, 256}), Contains("'P1b' is 500x256, expected 620x256"));
  REQUIRE_THROWS_WITH(MatReader("/nonexistent/x.mat"), Contains("no such file"));
  test::Scratch s("badmat");
  std::ofstream(s.dir / "bad.mat") << "not a mat file";
  REQUIRE_THROWS_WITH(MatReader(s.dir / "bad.mat"), Contains("bad.mat") && Contains("not a readable"));
}

TEST_CASE("Bayer split takes b gb gr r from FlatNet's positions and merges back", "[io][raw]") {
  auto raw = torch::arange(16, torch::kFloat32).reshape({4, 4});
  auto p = bayer_split(raw);
  REQUIRE(p.sizes() == torch::IntArrayRef({4, 2, 2}));
  CHECK(p[0][0][0].item<float>() == 0);  // b  = raw[0::2, 0::2]
  CHECK(p[1][0][0].item<float>() == 1);  // gb = raw[0::2, 1::2]
  CHECK(p[2][0][0].item<float>() == 4);  // gr = raw[1::2, 0::2]
  CHECK(p[3][0][0].item<float>() == 5);  // r  = raw[1::2, 1::2]
  CHECK(torch::equal(bayer_merge(p), raw));
}

TEST_CASE("double centring zeroes row and column means", "[io][raw]") {
  auto y = torch::rand({4, 10, 12}) + torch::arange(4).view({4, 1, 1});
  auto c = double_centre(y, Centring::plane);
  CHECK(c.mean(-1).abs().max().item<float>() < 1e-5);
  CHECK(c.mean(-2).abs().max().item<float>() < 1e-5);
  // FlatNet's variant adds back the mean over all planes: each plane shifts by a constant.
  auto f = double_centre(y, Centring::flatnet);
  auto diff = f - c;
  CHECK((diff - diff.mean({1, 2}, true)).abs().max().item<float>() < 1e-5);
  CHECK(diff[0].mean().item<float>() == Approx((y.mean() - y[0].mean()).item<float>()).margin(1e-5));
}

TEST_CASE("rotation matches skimage's warp convention", "[io][raw]") {
  auto img = torch::rand({1, 20, 30});
  CHECK(torch::equal(rotate_planes(img, 0.0), img));
  const double a = 0.05;
  auto r = rotate_planes(img, a);
  // output (row 10, col 12) samples input (sin*12 + cos*10, cos*12 - sin*10) bilinearly
  const double sr = std::sin(a) * 12 + std::cos(a) * 10, sc = std::cos(a) * 12 - std::sin(a) * 10;
  const int r0 = static_cast<int>(std::floor(sr)), c0 = static_cast<int>(std::floor(sc));
  const double fr = sr - r0, fc = sc - c0;
  auto v = [&](int i, int j) { return img[0][i][j].item<double>(); };
  const double expect = v(r0, c0) * (1 - fr) * (1 - fc) + v(r0, c0 + 1) * (1 - fr) * fc +
                        v(r0 + 1, c0) * fr * (1 - fc) + v(r0 + 1, c0 + 1) * fr * fc;
  CHECK(r[0][10][12].item<double>() == Approx(expect).margin(1e-5));
  // the bottom-left corner samples left of the frame: zero fill
  CHECK(rotate_planes(torch::ones({1, 20, 30}), 0.3)[0][19][0].item<float>() == 0.0f);
}

TEST_CASE("raw captures: 16-bit round trip and clear errors for size and bit depth", "[io][raw][errors]") {
  test::Scratch s("raw");
  RawGeometry g;
  auto codes = torch::randint(0, 1024, {1024, 1280}, torch::kInt32) * 64;
  write_gray16(s.dir / "ok.png", codes);
  CHECK(torch::equal(read_gray16(s.dir / "ok.png"), codes));
  auto cap = load_capture(s.dir / "ok.png", g);
  CHECK(cap.planes.sizes() == torch::IntArrayRef({4, 500, 620}));
  CHECK(cap.name == "ok.png");

  write_gray16(s.dir / "small.png", torch::zeros({100, 120}, torch::kInt32));
  REQUIRE_THROWS_WITH(load_capture(s.dir / "small.png", g), Contains("small.png") && Contains("120x100"));
  write_rgb8(s.dir / "rgb.png", torch::zeros({3, 8, 8}));
  REQUIRE_THROWS_WITH(load_capture(s.dir / "rgb.png", g), Contains("rgb.png") && Contains("single-channel"));
  std::ofstream(s.dir / "junk.png") << "junk";
  REQUIRE_THROWS_WITH(load_capture(s.dir / "junk.png", g), Contains("junk.png") && Contains("unreadable"));
}

namespace {

std::string file_bytes(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}
void put_bytes(const std::filesystem::path& p, const std::string& b) { std::ofstream(p, std::ios::binary) << b; }

// The PNG chunk layout: 4-byte length, 4-byte type, data, 4-byte CRC; a minimal grey image whose
// header declares w x h (its pixel data need not be there: the size check comes first).
std::string png_declaring(uint32_t w, uint32_t h) {
  auto be32 = [](uint32_t v) { return std::string{char(v >> 24), char(v >> 16), char(v >> 8), char(v)}; };
  auto chunk = [&](const std::string& type, const std::string& data) {
    const auto body = type + data;
    return be32(static_cast<uint32_t>(data.size())) + body +
           be32(static_cast<uint32_t>(
               crc32(0, reinterpret_cast<const Bytef*>(body.data()), static_cast<uInt>(body.size()))));
  };
  return std::string("\x89PNG\r\n\x1a\n", 8) +
         chunk("IHDR", be32(w) + be32(h) + std::string("\x08\x00\x00\x00\x00", 5)) +
         chunk("IDAT", std::string("\x78\x9c\x03\x00\x00\x00\x00\x01", 8)) + chunk("IEND", "");
}

}  // namespace

TEST_CASE("damaged images are refused in one line: truncated, bad CRC, cut-off JPEG, decompression bomb",
          "[io][image][errors]") {
  test::Scratch s("damaged");
  write_rgb8(s.dir / "ok.png", torch::rand({3, 32, 32}));
  write_gray16(s.dir / "raw.png", torch::randint(0, 65535, {64, 64}, torch::kInt32));
  const auto png = file_bytes(s.dir / "ok.png"), raw = file_bytes(s.dir / "raw.png");
  auto refused = [&](const std::filesystem::path& p, const std::string& what, bool gray16) {
    INFO(p.filename().string());
    try {
      if (gray16)
        read_gray16(p);
      else
        read_rgb(p);
      FAIL("no error");
    } catch (const Error& e) {
      const std::string m = e.what();
      CHECK_THAT(m, Contains(p.filename().string()) && Contains(what));
      CHECK(m.find('\n') == std::string::npos);  // one line
    }
  };
  put_bytes(s.dir / "half.png", png.substr(0, png.size() / 2));
  refused(s.dir / "half.png", "truncated PNG", false);
  put_bytes(s.dir / "half_raw.png", raw.substr(0, raw.size() - 20));
  refused(s.dir / "half_raw.png", "truncated PNG", true);
  auto flipped = png;
  flipped[flipped.size() / 2] ^= 0x55;  // inside the image data
  put_bytes(s.dir / "flipped.png", flipped);
  refused(s.dir / "flipped.png", "fails its CRC", false);
  put_bytes(s.dir / "bomb.png", png_declaring(60000, 60000));
  refused(s.dir / "bomb.png", "decompression bomb", false);
  refused(s.dir / "bomb.png", "decompression bomb", true);

  // A JPEG cut short decodes "successfully" as grey in libjpeg: refused by its missing end marker.
  const auto jpg_path = s.dir / "ok.jpg";
  {
    auto hwc = (torch::rand({32, 32, 3}) * 255).to(torch::kUInt8).contiguous();
    cv::Mat m(32, 32, CV_8UC3, hwc.data_ptr<uint8_t>());
    REQUIRE(cv::imwrite(jpg_path.string(), m));
  }
  CHECK(read_rgb(jpg_path).size(0) == 3);
  const auto jpg = file_bytes(jpg_path);
  put_bytes(s.dir / "cut.jpg", jpg.substr(0, jpg.size() * 2 / 3));
  refused(s.dir / "cut.jpg", "truncated JPEG", false);
  // The intact files still read.
  CHECK(read_rgb(s.dir / "ok.png").size(1) == 32);
  CHECK(read_gray16(s.dir / "raw.png").size(0) == 64);
}

TEST_CASE("sRGB transfer functions invert each other", "[io][image]") {
  auto x = torch::linspace(0, 1, 101, torch::kFloat64);
  CHECK(torch::allclose(linear_to_srgb(srgb_to_linear(x)), x, 1e-9, 1e-9));
  CHECK(srgb_to_linear(torch::tensor({0.5}, torch::kFloat64)).item<double>() == Approx(0.214041).epsilon(1e-5));
}

TEST_CASE("dataset lists: pairs, FlatNet-style roots, and errors", "[io][dataset][errors]") {
  test::Scratch s("lists");
  std::filesystem::create_directories(s.dir / "root" / "a");
  std::ofstream(s.dir / "root" / "a" / "m1.png") << "x";
  std::ofstream(s.dir / "root" / "a" / "g1.png") << "x";
  std::ofstream(s.dir / "meas.txt") << "a/m1.png\r\n\r\n";  // CRLF and blank lines are tolerated
  std::ofstream(s.dir / "gt.txt") << "a/g1.png\n";
  auto pairs = read_pairs({s.dir / "meas.txt", s.dir / "gt.txt", s.dir / "root"});
  REQUIRE(pairs.size() == 1);
  CHECK(pairs[0].meas == s.dir / "root" / "a" / "m1.png");

  std::ofstream(s.dir / "gt2.txt") << "a/g1.png\na/g1.png\n";
  REQUIRE_THROWS_WITH(read_pairs({s.dir / "meas.txt", s.dir / "gt2.txt", s.dir / "root"}),
                      Contains("meas.txt") && Contains("has 1 entries") && Contains("has 2"));
  std::ofstream(s.dir / "gt3.txt") << "a/missing.png\n";
  REQUIRE_THROWS_WITH(read_pairs({s.dir / "meas.txt", s.dir / "gt3.txt", s.dir / "root"}),
                      Contains("gt3.txt") && Contains("line 1") && Contains("missing.png"));
  std::ofstream(s.dir / "empty.txt") << "\n";
  REQUIRE_THROWS_WITH(read_pairs({s.dir / "empty.txt", s.dir / "gt.txt", s.dir / "root"}), Contains("list is empty"));
}

TEST_CASE("parallel_for_index starts nothing after an error, and rethrows the first", "[core][threads]") {
  std::vector<int> ran(50, 0);
  CHECK_THROWS_WITH(parallel_for_index(50, 1,
                                       [&](int64_t i) {
                                         ran[i] = 1;
                                         if (i == 3) throw Error("photo3.png", "corrupt");
                                       }),
                    Contains("photo3.png: corrupt"));
  CHECK(std::accumulate(ran.begin(), ran.end(), 0) == 4);  // 0..3 ran, 4..49 never started
}

TEST_CASE("all cores means the cores this process may run on (its affinity)", "[core][threads][cli]") {
  CHECK(all_cores() >= 1);
  const int before = at::get_num_threads();
  const int chosen = set_threads(0);
  CHECK(chosen >= 1);
  CHECK(chosen <= all_cores());
  set_threads(before);
  const auto pinned = test::run_shell("taskset -c 0 " + std::string(FLATNET_BINARY) +
                                      " bench --rows peak_gemm_fp32 --repeats 1 --warmup 0");
  REQUIRE(pinned.code == 0);
  CHECK_THAT(pinned.output, Contains("flatnet bench: 1 threads"));
}

TEST_CASE("by default threads take the cores that other work leaves free and --threads overrides it",
          "[core][threads][cli][solo]") {
  if (all_cores() < 2) SKIP_TEST("one core: nothing to leave free");
  // Two cores of this process's set; a busy loop holds the second for the whole command.
  const std::string cores = "taskset -c 0,1 ";
  const std::string bench = std::string(FLATNET_BINARY) + " bench --rows peak_gemm_fp32 --repeats 1 --warmup 0";
  const std::string busy = "taskset -c 1 sh -c \"while :; do :; done\" & B=$!; sleep 0.3; ";
  auto held = test::run_shell("bash -c " + test::q(busy + cores + bench + "; s=$?; kill $B; exit $s"));
  INFO(held.output);
  REQUIRE(held.code == 0);
  CHECK_THAT(held.output, Contains("flatnet bench: 1 threads"));
  auto asked = test::run_shell("bash -c " + test::q(busy + cores + bench + " --threads 2; s=$?; kill $B; exit $s"));
  INFO(asked.output);
  REQUIRE(asked.code == 0);
  CHECK_THAT(asked.output, Contains("flatnet bench: 2 threads"));
}

TEST_CASE("worker threads run single-threaded, and BLAS from two workers at once gives each its own answer",
          "[core][threads]") {
  const int before = at::get_num_threads();
  set_threads(2);
  std::vector<int> seen(4, 0);
  // Two workers each multiply their own matrices many times at once (OpenBLAS's OpenMP build shares
  // its multithreaded buffers between callers); every product must equal the one made alone.
  const auto a = torch::randn({300, 200}), b = torch::randn({200, 250});
  const auto expected = torch::matmul(a, b);
  std::vector<double> worst(4, 0);
  parallel_for_index(4, 2, [&](int64_t i) {
    seen[i] = at::get_num_threads();
    for (int k = 0; k < 20; ++k)
      worst[i] = std::max(worst[i], (torch::matmul(a * (i + 1), b) / (i + 1) - expected).abs().max().item<double>());
  });
  set_threads(before);
  for (int i = 0; i < 4; ++i) {
    CHECK(seen[i] == 1);
    CHECK(worst[i] < 1e-3);
  }
}

TEST_CASE("camera-file keys: one row each, written and read back whole, each range checked once by its row",
          "[io][camera]") {
  CameraConfig c;
  c.name = "rows";
  c.raw.raw_height = 512, c.raw.raw_width = 640, c.raw.adc_bits = 12, c.raw.rotation = 0.01;
  c.raw.crop = {2, 4, 200, 300};
  c.raw.centring = Centring::level;
  c.raw.hot_pixels = {{3, 5}};
  c.scene_size = 128, c.tikhonov_lambda = 2e-4, c.tv_lambda = 3e-4;
  c.noise_gain = 1e-4, c.noise_floor = 2e-6, c.dark = 0.01;
  c.fit_threshold = 2, c.leak_threshold = 3, c.open_light = 4, c.display_gamma = 1.25;
  c.colour_mix = {{{0, 0.1, 0.9}}, {{0.1, 0.8, 0.1}}, {{0.1, 0.8, 0.1}}, {{0.9, 0.1, 0}}};
  const auto text = camera_geometry_yaml(c);
  const auto back = camera_from_yaml_text(text, "rows.yaml");
  CHECK(camera_geometry_yaml(back) == text);
  CHECK((back.raw.hot_pixels == c.raw.hot_pixels));
  CHECK(back.display_gamma == 1.25);
  // Every key the writer states is a key of the rows, and every row is listed with its range.
  std::set<std::string> listed;
  for (const auto& k : camera_file_keys()) listed.insert(k.key);
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    INFO(line);
    CHECK(listed.count(line.substr(0, line.find(':'))) == 1);
  }
  CHECK(listed.count("calibration") == 1);
  CHECK(listed.count("bench.second_term") == 1);
  // Out of its range, a key is named with the range its row states.
  const std::vector<std::pair<std::string, std::string>> bad = {
      {"adc_bits: 17", "adc_bits is 1 to 16; got 17"},
      {"noise_gain: 1.5", "noise_gain is [0, 1) full scale"},
      {"fit_threshold: 0.5", "fit_threshold is 0 (the camera fit's own) or a ratio within [1, 1000]"},
      {"tikhonov_lambda: 0", "tikhonov_lambda is (0, 1e4]"},
      {"open_light: -1", "open_light is 0 (unknown)"},
      {"raw_width: 641", "raw_height and raw_width must be positive and even"}};
  for (const auto& [line, message] : bad) {
    INFO(line);
    CHECK_THROWS_WITH(camera_from_yaml_text(line + "\n", "bad.yaml"), Contains("bad.yaml") && Contains(message));
  }
}
