// recon/ and eval/: Tikhonov, TV, the Reconstructor interface and its batch loop, metrics.
#include <sys/stat.h>

#include <fstream>

#include "catch_torch.hpp"

#include "io/camera_config.hpp"
#include "core/util.hpp"
#include "eval/inversion_report.hpp"
#include "eval/metrics.hpp"
#include "eval/report.hpp"
#include "eval/thesis_report.hpp"
#include "helpers.hpp"
#include "nn/onednn_conv.hpp"
#include "optics/camera.hpp"
#include "optics/separable_inverse.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "nn/model_file.hpp"
#include "recon/data_consistency.hpp"
#include "recon/methods.hpp"
#include "recon/reconstructor.hpp"
#include "recon/tikhonov.hpp"
#include "recon/batch.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {
Calibration random_calibration(int64_t h, int64_t w, int64_t n, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  return {at::randn({4, h, n}, gen, torch::kFloat64), at::randn({4, w, n}, gen, torch::kFloat64)};
}
torch::Tensor forward(const Calibration& c, const torch::Tensor& X) {
  return torch::matmul(torch::matmul(c.P.to(torch::kFloat32), X), c.Q.to(torch::kFloat32).transpose(1, 2));
}
}  // namespace

TEST_CASE("Tikhonov inverts a well-conditioned separable operator", "[recon][tikhonov]") {
  auto calib = random_calibration(40, 48, 16, 2);
  auto X = torch::rand({2, 4, 16, 16});
  Tikhonov tik(calib, 1e-9);
  auto Xh = tik(forward(calib, X));
  CHECK((Xh - X).abs().max().item<float>() < 1e-3);
  // equals the normal equations (P^T P x Q^T Q + lambda x = P^T Y Q) for a sizeable lambda
  Tikhonov reg(calib, 50.0);
  auto Y = forward(calib, X);
  auto Z = reg(Y);
  auto P = calib.P.to(torch::kFloat32), Q = calib.Q.to(torch::kFloat32);
  auto lhs = torch::matmul(torch::matmul(P.transpose(1, 2), forward(calib, Z)), Q) + 50.0 * Z;
  auto rhs = torch::matmul(torch::matmul(P.transpose(1, 2), Y), Q);
  CHECK(((lhs - rhs).norm() / rhs.norm()).item<float>() < 1e-4);
}

TEST_CASE("TV gradient and divergence are negative adjoints", "[recon][tv]") {
  auto x = torch::randn({3, 9, 11}, torch::kFloat64);
  auto px = torch::randn({3, 9, 11}, torch::kFloat64), py = torch::randn({3, 9, 11}, torch::kFloat64);
  auto [gx, gy] = tv_gradient(x);
  const double lhs = ((gx * px).sum() + (gy * py).sum()).item<double>();
  const double rhs = -(x * tv_divergence(px, py)).sum().item<double>();
  CHECK(lhs == Approx(rhs).epsilon(1e-10));
}

TEST_CASE("TV reconstruction is non-negative and fits piecewise-constant scenes", "[recon][tv]") {
  auto calib = random_calibration(40, 48, 16, 3);
  auto X = torch::zeros({1, 4, 16, 16});
  X.slice(2, 4, 12).slice(3, 4, 12).fill_(1.0);
  auto Y = forward(calib, X) + 0.5 * torch::randn({1, 4, 40, 48});
  TVOptions opt;
  opt.lambda = 20.0;
  opt.iterations = 100;
  opt.tikhonov_lambda = 1.0;
  auto tv = TVSolver(calib, opt)(Y);
  auto tik = Tikhonov(calib, 1.0)(Y);
  CHECK(tv.min().item<float>() >= 0.0f);
  CHECK((tv - X).norm().item<float>() < (tik - X).norm().item<float>());
}

TEST_CASE("Tikhonov on a golden capture with the shipped calibration beats 10 dB", "[recon][golden]") {
  const auto camera = load_camera_config(default_camera_path());
  const auto calib = load_calibration(camera.calibration, camera);
  Tikhonov tik(calib, camera.tikhonov_lambda);
  auto cap = load_capture(test::data_dir() / "golden" / "inet_n02980441_castle_raw.png", camera.raw);
  auto rgb = planes_to_srgb(tik(cap.planes.unsqueeze(0))[0]);
  auto gt = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png");
  CHECK(psnr(rgb, gt) > 10.0);
}

TEST_CASE("PSNR and SSIM match their definitions and skimage", "[eval][metrics]") {
  auto a = torch::full({3, 32, 32}, 0.5);
  CHECK(psnr(a, a + 0.1) == Approx(20.0).epsilon(1e-4));  // MSE 0.01
  CHECK(ssim(a, a) == Approx(1.0));
  auto x = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png");
  auto y = read_rgb(test::data_dir() / "golden" / "inet_n02088094_Afghan_hound_scene.png");
  // skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
  //   use_sample_covariance=False, data_range=1, channel_axis=2) and peak_signal_noise_ratio
  CHECK(ssim(x, y) == Approx(0.09807770334584061).epsilon(1e-5));
  CHECK(psnr(x, y) == Approx(8.51326925956448).epsilon(1e-5));
}

TEST_CASE("eval reports spread over images and brightness: a reconstruction that darkens or whitens shows", "[eval]") {
  test::Scratch s("eval_brightness");
  for (const auto* d : {"gt", "out/half", "out/white"}) std::filesystem::create_directories(s.dir / d);
  auto gen = at::detail::createCPUGenerator(3);
  for (int i = 0; i < 3; ++i) {
    const auto gt = (at::rand({3, 32, 32}, gen) * 0.2 + 0.2 * i).clamp(0, 1);  // images of different brightness
    const auto name = "img" + std::to_string(i) + ".png";
    write_rgb8(s.dir / "gt" / name, gt);
    write_rgb8(s.dir / "out/half" / name, gt * 0.5);
    write_rgb8(s.dir / "out/white" / name, torch::ones_like(gt));
  }
  EvalOptions eval_options;
  eval_options.gt = s.dir / "gt", eval_options.out = s.dir / "out", eval_options.sheet_rows = 2;
  const auto scores = evaluate(eval_options);
  REQUIRE(scores.size() == 2);
  CHECK(scores[0].method == "half");
  CHECK(scores[0].brightness == Approx(0.5).margin(0.01));
  CHECK(scores[1].brightness > 2.0);
  CHECK(scores[0].psnr_sd > 0);  // brighter images lose more to halving: PSNR varies
  CHECK(format_table(scores).find("+-") != std::string::npos);
  CHECK(read_lines(s.dir / "out" / "metrics.csv").at(0) ==
        "image,method,psnr,ssim,mean_output,mean_truth,colour_kept,detail_kept,stripes");
  // Halving the image halves its colourfulness and detail (both are linear in the values, up to
  // 8-bit rounding); a white image keeps neither.
  CHECK(scores[0].colour_kept == Approx(0.5).margin(0.02));
  CHECK(scores[0].detail_kept == Approx(0.5).margin(0.02));
  CHECK(scores[1].colour_kept == Approx(0.0).margin(1e-9));
  CHECK(scores[1].detail_kept == Approx(0.0).margin(1e-9));
  CHECK(format_table(scores).find("colour") != std::string::npos);
}

TEST_CASE("colourfulness and detail match their definitions (Hasler-Suesstrunk 2003, Sobel of the luma)", "[eval]") {
  const auto x = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png");
  // numpy: sqrt(sd(rg)^2 + sd(yb)^2) + 0.3 sqrt(mean(rg)^2 + mean(yb)^2) on values / 255, and
  // scipy.signal.correlate2d(luma, sobel, 'valid') magnitudes' mean.
  CHECK(colourfulness(x) == Approx(0.266866453557).epsilon(1e-6));
  CHECK(luma_detail(x) == Approx(0.438046295424).epsilon(1e-6));
  const auto grey = x.mean(0, true).repeat({3, 1, 1});
  CHECK(colourfulness(grey) == Approx(0.0).margin(1e-12));  // a grey image has no colour
  CHECK(luma_detail(torch::full({3, 16, 16}, 0.3)) == Approx(0.0).margin(1e-12));
  CHECK(luma_detail(x.flip(2)) == Approx(luma_detail(x)).epsilon(1e-9));  // a mirror image has the same detail
}

TEST_CASE("stripe energy: rows and columns that stand out from their trend, in 8-bit codes", "[eval]") {
  const auto truth =
      read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png").slice(1, 0, 64).slice(2, 0, 64);
  CHECK(stripe_energy(truth, truth) == Approx(0.0).margin(1e-12));
  // Rows alternating 0, +4, 0, -4 codes: 2.1221 (a Python loop over the same definition).
  const auto rows = torch::tensor({0.0, 1.0, 0.0, -1.0}, torch::kFloat64).repeat(16).view({1, 64, 1});
  const auto striped = truth.to(torch::kFloat64) + 4.0 / 255 * rows;
  CHECK(stripe_energy(striped, truth) == Approx(2.1220818537564097).epsilon(1e-9));
  CHECK(stripe_energy(truth + 4.0 / 255 * rows.view({1, 1, 64}), truth) == Approx(2.1220818537564097).epsilon(1e-9));
  // A constant error is all trend; a slow tilt of 13 codes across the image almost all (0.147).
  CHECK(stripe_energy(truth.to(torch::kFloat64) + 0.1, truth) == Approx(0.0).margin(1e-9));
  const auto tilt = 0.05 * torch::arange(64, torch::kFloat64).view({1, 64, 1}) / 64;
  CHECK(stripe_energy(truth.to(torch::kFloat64) + tilt, truth) == Approx(0.1473242524111722).epsilon(1e-9));
  CHECK_THROWS(stripe_energy(truth, truth.slice(1, 0, 32)));
}

TEST_CASE("reconstructions never overwrite a capture, and two captures of one name are refused", "[recon][outputs]") {
  test::Scratch s("outputs");
  const auto in = s.dir / "in", other = s.dir / "other";
  std::filesystem::create_directories(in);
  std::filesystem::create_directories(other);
  const auto capture = test::data_dir() / "golden" / "bsds_16052_raw.png";
  std::filesystem::copy_file(capture, in / "a.png");
  std::filesystem::copy_file(capture, other / "a.png");
  const auto before = read_bytes(in / "a.png");
  // --out equal to the input folder, given as the folder, a pattern or a list.
  CHECK_THROWS_WITH(check_output_names({in / "a.png"}, in), Contains("recon.out") && Contains("overwrite a capture"));
  CHECK_THROWS_WITH(check_output_names({in / "a.png"}, s.dir / "in" / "."), Contains("overwrite"));
  // Two captures named a.png from different folders would make one output.
  CHECK_THROWS_WITH(check_output_names({in / "a.png", other / "a.png"}, s.dir / "out"),
                    Contains("same name") && Contains("a.png"));
  CHECK_NOTHROW(check_output_names({in / "a.png"}, s.dir / "out"));
  // Through the command line: exit 2, one line, the capture untouched.
  for (const std::string& cmd : std::vector<std::string>{
           "recon --method tikhonov",
           "infer --model " + test::q(test::source_dir() / "models" / "flatnet-sim-transpose.flatnet")}) {
    INFO(cmd);
    const auto r = test::run_flatnet(cmd + " --input " + test::q(in) + " --out " + test::q(in));
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("overwrite a capture"));
    CHECK(read_bytes(in / "a.png") == before);
  }
}

// ---- The one reconstruction interface -------------------------------------------------------------

TEST_CASE("Reconstructor: classical engines are the solver on the capture without its light level, in sRGB",
          "[recon][interface]") {
  const auto camera = load_camera_config(default_camera_path());
  const auto calib = load_calibration(camera.calibration, camera);
  const auto capture = load_capture(test::data_dir() / "golden" / "inet_n02980441_castle_raw.png", camera.raw);
  const auto planes = capture.planes.unsqueeze(0);  // {1,4,500,620}
  auto engine = make_classical(calib, camera, {ClassicalMethod::tikhonov, 0.0});
  const auto image = engine->reconstruct(planes);
  CHECK(image.sizes() == torch::IntArrayRef({1, 3, camera.scene_size, camera.scene_size}));
  const Tikhonov tik(calib, camera.tikhonov_lambda);
  CHECK(torch::equal(image, planes_to_srgb(tik(without_level(planes, camera.raw.centring)))));
  CHECK_THAT(engine->describe(), Contains("Tikhonov"));
  // Another lambda gives another image; batches reconstruct sample by sample.
  auto other = make_classical(calib, camera, {ClassicalMethod::tikhonov, camera.tikhonov_lambda * 100});
  CHECK_FALSE(torch::equal(other->reconstruct(planes), image));
  const auto two = engine->reconstruct(torch::cat({planes, planes.flip({3})}));
  CHECK(torch::allclose(two[0], image[0], 0, 1e-6));
}

TEST_CASE("Reconstructor factory: every method by name, and clear errors", "[recon][interface]") {
  test::Scratch s("factory");
  ReconstructorSpec spec;
  spec.camera = load_camera_config(default_camera_path());
  spec.method = "wiener";
  CHECK_THROWS_WITH(make_reconstructor(spec), Contains("tikhonov, tv, flatnet or opencv") && Contains("wiener"));
  spec.method = "tv";
  auto tv = make_reconstructor(spec);
  CHECK_THAT(tv.engine->describe(), Contains("TV"));
  spec.method = "tikhonov";
  spec.camera.calibration.clear();
  CHECK_THROWS_WITH(make_reconstructor(spec), Contains("no calibration"));
  spec.calibration = s.dir / "missing.mat";
  CHECK_THROWS_WITH(make_reconstructor(spec), Contains("missing.mat"));
  spec.method = "flatnet";
  spec.model = test::source_dir() / "models" / "flatnet-sim-transpose.flatnet";
  spec.use_camera = false;  // the model's own preprocessing
  auto built = make_reconstructor(spec);
  CHECK_THAT(built.engine->describe(), Contains("FlatNet flatnet-sim-transpose.flatnet (fp32)"));
  auto model = load_model_file(spec.model);
  CHECK(built.camera.raw.crop == model.camera.raw.crop);
  // The engine is the generator itself (prepared for inference: within float rounding).
  const auto planes =
      load_capture(test::data_dir() / "golden" / "inet_n02980441_castle_raw.png", built.camera.raw).planes.unsqueeze(0);
  torch::Tensor expected;
  {
    c10::InferenceMode guard;
    expected = model.generator->forward(planes);
  }
  CHECK(torch::allclose(built.engine->reconstruct(planes), expected, 0, 1e-4));
  spec.method = "opencv";
  spec.model = s.dir / "missing.onnx";
  CHECK_THROWS_WITH(make_reconstructor(spec), Contains("missing.onnx"));
}

namespace {

// A method that exists only in the tests: the capture's mean light, grey, at the camera's scene size.
// Adding it is its factory and one register_method call; nothing in src/ names it.
class MeanGrey final : public Reconstructor {
 public:
  explicit MeanGrey(int64_t size) : size_(size) {}
  std::string describe() const override { return "mean grey"; }
  torch::Tensor reconstruct(const torch::Tensor& planes) override {  // {B,4,h,w} -> {B,3,N,N}
    const auto mean = planes.mean({1, 2, 3}).clamp(0, 1).view({-1, 1, 1, 1});
    return mean.expand({planes.size(0), 3, size_, size_}).contiguous();
  }

 private:
  int64_t size_;
};

BuiltReconstructor build_mean_grey(const ReconstructorSpec& spec) {
  return {std::make_unique<MeanGrey>(spec.camera.scene_size), spec.camera, nullptr, "a test method judges nothing"};
}

// Registers the test's method for the length of one test.
struct ScopedMethod {
  explicit ScopedMethod(ReconstructionMethod m) : name(m.name) { register_method(std::move(m)); }
  ~ScopedMethod() { unregister_method(name); }
  std::string name;
};

}  // namespace

TEST_CASE("a reconstruction method registered in a test is offered by the factory, recon and the report",
          "[recon][interface]") {
  const auto builtin = reconstruction_methods().size();
  CHECK(method_names(MethodInput::calibration) == "tikhonov | tv");
  CHECK(method_names(MethodInput::model_file) == "flatnet | opencv");
  {
    const ScopedMethod grey(
        {"mean-grey", "Mean grey", "the capture's mean light", MethodInput::calibration, {}, false, build_mean_grey});
    CHECK(reconstruction_methods().size() == builtin + 1);
    CHECK(method_names(MethodInput::calibration) == "tikhonov | tv | mean-grey");
    // The factory by name, with nothing else changed.
    ReconstructorSpec spec;
    spec.camera = load_camera_config(default_camera_path());
    spec.method = "mean-grey";
    auto built = make_reconstructor(spec);
    CHECK(built.engine->describe() == "mean grey");
    const auto planes = torch::full({2, 4, 8, 8}, 0.25);
    const auto image = built.engine->reconstruct(planes);
    CHECK(image.sizes() == torch::IntArrayRef({2, 3, spec.camera.scene_size, spec.camera.scene_size}));
    CHECK(image.max().item<double>() == Approx(0.25));
    // recon's check and the report's column parser know it; its errors list it.
    CHECK(require_method("mean-grey", MethodInput::calibration, "recon.method").label == "Mean grey");
    CHECK_THROWS_WITH(require_method("mean-grey", MethodInput::model_file, "infer.method"),
                      Contains("must be flatnet or opencv") && Contains("'mean-grey'"));
    CHECK_THROWS_WITH(require_method("wiener", MethodInput::calibration, "recon.method"),
                      Contains("must be tikhonov, tv or mean-grey, got 'wiener'"));
    const auto column = parse_report_method("mean-grey");
    CHECK(column.kind == "mean-grey");
    CHECK(column.name == "mean-grey");
    // A second method of that name, a name that is a path, the report's kind and a method without a
    // factory are refused.
    CHECK_THROWS_WITH(register_method({"mean-grey", "", "", MethodInput::calibration, {}, false, build_mean_grey}),
                      Contains("exists"));
    CHECK_THROWS_WITH(register_method({"../x", "", "", MethodInput::calibration, {}, false, build_mean_grey}),
                      Contains("method's name"));
    CHECK_THROWS_WITH(register_method({"model", "", "", MethodInput::model_file, {}, false, build_mean_grey}),
                      Contains("'model'"));
    CHECK_THROWS_WITH(register_method({"no-factory", "", "", MethodInput::calibration, {}, false, {}}),
                      Contains("no factory"));
  }
  // Gone with its scope: the registry is as it was, and the name is unknown again.
  CHECK(reconstruction_methods().size() == builtin);
  CHECK(find_method("mean-grey") == nullptr);
  CHECK_THROWS_WITH(parse_report_method("mean-grey"), Contains("expected tikhonov, tv or NAME=MODEL.flatnet"));
}

TEST_CASE("reconstruct_files: one batch loop writes a PNG per capture for any engine", "[recon][interface]") {
  test::Scratch s("batchloop");
  const auto camera = load_camera_config(default_camera_path());
  std::vector<std::filesystem::path> captures;
  for (const auto& p : list_images(test::data_dir() / "golden", {".png"}))
    if (p.stem().string().find("_raw") != std::string::npos) captures.push_back(p);
  REQUIRE(captures.size() >= 2);
  // A stand-in engine that counts its calls and returns grey images.
  struct Grey final : Reconstructor {
    int calls = 0;
    std::string describe() const override { return "grey"; }
    torch::Tensor reconstruct(const torch::Tensor& planes) override {
      ++calls;
      return torch::full({planes.size(0), 3, 16, 16}, 0.5);
    }
  } grey;
  BatchOptions o;
  o.out = s.dir / "out";
  o.batch = 3;
  o.progress = false;
  const auto report = reconstruct_files(grey, camera, captures, o);
  CHECK(report.count == static_cast<int64_t>(captures.size()));
  CHECK(grey.calls == static_cast<int>((captures.size() + 2) / 3));
  for (const auto& c : captures) {
    const auto written = read_rgb(o.out / c.filename());
    CHECK(written.sizes() == torch::IntArrayRef({3, 16, 16}));
  }
  o.batch = 0;
  CHECK_THROWS_WITH(reconstruct_files(grey, camera, captures, o), Contains("recon.batch: must be at least 1"));
  o.batch = 1;
  CHECK_THROWS_WITH(reconstruct_files(grey, camera, {}, o), Contains("no captures"));
}

TEST_CASE("inversion products: an exact inverse is all diagonal, a shifted one is found at its offset",
          "[eval][inversion]") {
  const auto q = std::get<0>(torch::linalg_qr(torch::randn({40, 16}, torch::kFloat64)));  // {40,16} orthonormal columns
  const auto [product, exact] = inversion_product(q, q);
  CHECK(torch::allclose(product, torch::eye(16, torch::kFloat64), 1e-9, 1e-9));
  CHECK(exact.diagonal == Approx(1.0));
  CHECK(exact.band == Approx(1.0));
  CHECK(exact.offset == 0);
  // W whose column i is Phi's column i - 5 (the first five zero): W^T Phi has its ones at i - j = 5.
  auto shifted = torch::zeros_like(q);
  shifted.slice(1, 5).copy_(q.slice(1, 0, 11));
  const auto [p2, s2] = inversion_product(shifted, q);
  CHECK(s2.diagonal < 1e-12);
  CHECK(s2.band > 0.99);
  CHECK(p2[5][0].item<double>() == Approx(1.0));  // row i = 5 (W's column 5 is Phi's column 0): offset i - j = 5
  CHECK(s2.offset == 5);
  CHECK_THROWS(inversion_product(q, q.slice(1, 0, 8)));
  // Stray rows: an output row that inverts nothing (W's zero columns 0-4) or a far-away scene row.
  CHECK(exact.stray_rows.empty());
  CHECK(s2.stray_rows == std::vector<int64_t>{0, 1, 2, 3, 4});
  auto one_wrong = q.clone();
  one_wrong.select(1, 9).copy_(q.select(1, 2));  // output row 9 shows scene row 2
  const auto [p3, s3] = inversion_product(one_wrong, q);
  CHECK(s3.offset == 0);
  CHECK(s3.stray_rows == std::vector<int64_t>{9});
  CHECK(index_ranges({0, 1, 2, 4, 7, 8, 9}) == "0-2, 4, 7-9");
  CHECK(index_ranges({}) == "none");
}

TEST_CASE("Tikhonov through oneDNN's GEMM equals the reference products, batches and broadcasts included",
          "[recon][onednn]") {
  torch::manual_seed(9);
  // onednn_bmm against torch::bmm, with either operand broadcast over the batch.
  const auto a = torch::randn({3, 7, 5}), b = torch::randn({3, 5, 4});
  CHECK(torch::allclose(onednn_bmm(a, b), torch::bmm(a, b), 1e-5, 1e-5));
  CHECK(torch::allclose(onednn_bmm(a.slice(0, 0, 1), b), torch::matmul(a.slice(0, 0, 1), b), 1e-5, 1e-5));
  CHECK(torch::allclose(onednn_bmm(a, b.slice(0, 0, 1)), torch::matmul(a, b.slice(0, 0, 1)), 1e-5, 1e-5));
  CHECK_THROWS(onednn_bmm(a, torch::randn({3, 4, 4})));
  // Transposed views are read in place, other layouts copied first: the same products.
  const auto at = torch::randn({3, 5, 7}), bt = torch::randn({3, 4, 5});
  CHECK(torch::allclose(onednn_bmm(at.transpose(1, 2), bt.transpose(1, 2)),
                        torch::bmm(at.transpose(1, 2), bt.transpose(1, 2)), 1e-5, 1e-5));
  CHECK(torch::allclose(onednn_bmm(at.slice(0, 0, 1).transpose(1, 2), b),
                        torch::matmul(at.slice(0, 0, 1).transpose(1, 2), b), 1e-5, 1e-5));
  const auto permuted = torch::randn({5, 3, 7}).permute({1, 2, 0});  // {3,7,5}, neither layout
  CHECK(torch::allclose(onednn_bmm(permuted, b), torch::bmm(permuted, b), 1e-5, 1e-5));
  // The reconstruction: batch 1 and 2, against the optics layer's reference order.
  Calibration c;
  c.P = torch::randn({4, 40, 16}) / std::sqrt(40.0);
  c.Q = torch::randn({4, 36, 16}) / std::sqrt(36.0);
  const Tikhonov tik(c, 1e-3);
  const auto v = separable_inverse(c.P, c.Q, 1e-3);
  for (int64_t batch : {1, 2}) {
    const auto Y = torch::randn({batch, 4, 40, 36});
    const auto reference = apply_separable_inverse(v.ULt, v.UR, v.VL, v.VRt, v.filter, Y);
    const auto fast = tik(Y);
    REQUIRE(fast.sizes() == reference.sizes());
    CHECK((fast - reference).abs().max().item<double>() < 1e-4 * reference.abs().max().item<double>());
  }
}

TEST_CASE("the differentiable oneDNN product has torch::matmul's value and gradients, broadcasts included",
          "[nn][onednn]") {
  torch::manual_seed(10);
  for (const auto& [batch_a, batch_b] : std::vector<std::pair<int64_t, int64_t>>{{3, 3}, {1, 3}, {3, 1}}) {
    INFO(batch_a << " x " << batch_b);
    const auto a0 = torch::randn({batch_a, 6, 5}), b0 = torch::randn({batch_b, 5, 4});
    const auto weights = torch::randn({3, 6, 4});  // a loss that weighs every output differently
    auto a1 = a0.clone().requires_grad_(), b1 = b0.clone().requires_grad_();
    auto a2 = a0.clone().requires_grad_(), b2 = b0.clone().requires_grad_();
    const auto mine = onednn_matmul_autograd(a1, b1), reference = torch::matmul(a2, b2);
    CHECK(torch::allclose(mine, reference, 1e-5, 1e-5));
    (mine * weights).sum().backward();
    (reference * weights).sum().backward();
    CHECK(torch::allclose(a1.grad(), a2.grad(), 1e-4, 1e-5));
    CHECK(torch::allclose(b1.grad(), b2.grad(), 1e-4, 1e-5));
  }
}

// The camera fit of a tiny model trained with `camera` whose training config records `data.camera`
// as `recorded` (a path on the training machine), with `why` set when there is none.
static std::shared_ptr<const CameraFit> fit_of_model_recording(const std::filesystem::path& dir,
                                                               const CameraConfig& camera, const std::string& recorded,
                                                               std::string& why) {
  auto config = Config::load(
      {}, {"model.unet.width=2", "model.inversion.init=random", "model.level_input=true", "data.camera=" + recorded});
  Generator g(generator_options(config, camera, false));
  const auto file = dir / "m.flatnet";
  save_model_file(file, g, config, camera);
  return model_camera_fit(load_model_file(file), why);
}

TEST_CASE("a model trained elsewhere finds its camera among flatnet's own in a camera's folder too",
          "[recon][camera-fit]") {
  // The training machine's path is gone here; the camera lies under configs/cameras/ in a folder of
  // its own (the prototype's calibration beside its camera.yaml), and is found there by that place.
  test::Scratch s("camera_elsewhere");
  const auto camera =
      load_camera_config(test::source_dir() / "configs" / "cameras" / "flatnet_prototype" / "camera.yaml");
  std::string why;
  const auto fit = fit_of_model_recording(s.dir, camera, "/nowhere/configs/cameras/flatnet_prototype/camera.yaml", why);
  INFO(why);
  CHECK(fit != nullptr);
}

TEST_CASE("a model trained in another checkout finds a camera kept among flatnet's models", "[recon][camera-fit]") {
  // The shipped calibration-free model records the identified camera's path in the checkout it was
  // trained in (.../models/stages/identified-camera/camera_train.yaml); elsewhere it is found at the
  // same place among flatnet's own models, so its captures' fit is still judged.
  test::Scratch s("camera_in_models");
  const auto camera =
      load_camera_config(test::source_dir() / "models" / "stages" / "identified-camera" / "camera_train.yaml");
  std::string why;
  const auto fit =
      fit_of_model_recording(s.dir, camera, "/nowhere/checkout/models/stages/identified-camera/camera_train.yaml", why);
  INFO(why);
  CHECK(fit != nullptr);
  // A path that names no camera among the models stays unjudged, with the reason.
  std::string why_not;
  CHECK(fit_of_model_recording(s.dir, camera, "/nowhere/checkout/models/no_such_camera.yaml", why_not) == nullptr);
  CHECK_THAT(why_not, Contains("names no calibration"));
  // The recorded path is the model file's word: a file there that is no camera leaves the model usable
  // and unjudged, and a path that climbs out with `..` is not looked for among flatnet's models.
  const auto not_a_camera = s.dir / "notes.txt";
  std::ofstream(not_a_camera) << "a file a hostile model names as its camera\n";
  for (const auto& recorded : {not_a_camera.string(), std::string("/nowhere/models/stages/../stages/identified-camera/"
                                                                  "camera_train.yaml")}) {
    INFO(recorded);
    std::string why_hint;
    CHECK(fit_of_model_recording(s.dir, camera, recorded, why_hint) == nullptr);
    CHECK_THAT(why_hint, Contains("names no calibration"));
  }
}

TEST_CASE("whatever lies behind a model's recorded camera is passed over, never an error",
          "[recon][camera-fit][hostile]") {
  test::Scratch s("camera_hint_hostile");
  // The model's camera, and a camera file of the same name and geometry whose calibration is broken.
  const std::string geometry =
      "name: hinted\nraw_height: 64\nraw_width: 64\ncrop: [0, 0, 20, 24]\nscene_size: 16\ncentring: level\n";
  const auto camera = camera_from_yaml_text(geometry, "hinted.yaml");
  auto nan_calib = Calibration{torch::rand({4, 20, 16}, torch::kFloat64), torch::rand({4, 24, 16}, torch::kFloat64)};
  nan_calib.P[0][0][0] = NAN;
  save_calibration(s.dir / "nan.mat", nan_calib);
  std::ofstream(s.dir / "nan.yaml") << geometry << "calibration: nan.mat\n";
  std::ofstream(s.dir / "sparse.mat").close();
  std::filesystem::resize_file(s.dir / "sparse.mat", 2ull << 30);  // 2 GB of holes
  std::ofstream(s.dir / "sparse.yaml") << geometry << "calibration: sparse.mat\n";
  std::filesystem::create_symlink(s.dir / "loop_b.yaml", s.dir / "loop_a.yaml");
  std::filesystem::create_symlink(s.dir / "loop_a.yaml", s.dir / "loop_b.yaml");
  REQUIRE(mkfifo((s.dir / "fifo.yaml").c_str(), 0600) == 0);
  for (const auto& recorded : {s.dir / "nan.yaml", s.dir / "sparse.mat", s.dir / "sparse.yaml", s.dir / "loop_a.yaml",
                               s.dir / "fifo.yaml", s.dir / (std::string(300, 'x') + ".yaml")}) {
    INFO(recorded);
    std::string why;
    std::shared_ptr<const CameraFit> fit;
    CHECK_NOTHROW(fit = fit_of_model_recording(s.dir, camera, recorded.string(), why));
    CHECK(fit == nullptr);
    CHECK_THAT(why, Contains("names no calibration"));
  }
}

TEST_CASE("a model trained with the data-consistency layer applies it at inference unless told otherwise",
          "[recon][interface][consistency]") {
  ModelSpec trained, plain;
  trained.consistency_strength = 10, trained.consistency_blur = 1;
  ReconstructorSpec spec;  // the model's own, by default
  CHECK(consistency_of(spec, trained).strength == 10);
  CHECK(consistency_of(spec, trained).blur == 1);
  CHECK(consistency_of(spec, plain).strength == 0);  // a model trained without it: none
  spec.data_consistency = 0;                         // off
  CHECK(consistency_of(spec, trained).strength == 0);
  spec.data_consistency = 3, spec.consistency_blur = 0;  // the user's, over the model's
  CHECK(consistency_of(spec, trained).strength == 3);
  CHECK(consistency_of(spec, trained).blur == 0);
  spec.consistency_blur = ReconstructorSpec::kModelsOwn;  // a strength for a plain model: no blur of its own
  CHECK(consistency_of(spec, plain).blur == 0);
  // End to end: the model file records it, and the engine applies it.
  test::Scratch s("model_consistency");
  auto m = load_model_file(test::source_dir() / "models" / "flatnet-sim-transpose.flatnet");
  auto identity = model_identity(m);
  identity.spec.consistency_strength = 10, identity.spec.consistency_blur = 1;
  save_model_file(s.dir / "dc.flatnet", m.generator, identity);
  ReconstructorSpec own;
  own.method = "flatnet";
  own.use_camera = false;
  own.model = s.dir / "dc.flatnet";
  const auto built = make_reconstructor(own);
  CHECK(built.corrected);
  CHECK_THAT(built.engine->describe(), Contains("data consistency (c 10"));
}
