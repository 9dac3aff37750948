// flatnet mask train | eval | report: learned FlatCam masks against MLS and FlatNet's 02 mask.
#include <fstream>
#include <iomanip>
#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/metrics.hpp"
#include "eval/plot.hpp"
#include "eval/tables.hpp"
#include "optics/separable_camera.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "optics/codes.hpp"
#include "optics/simulator.hpp"
#include "train/config.hpp"
#include "train/mask_trainer.hpp"
#include "train/separable_trainer.hpp"

namespace flatnet::cli {

namespace {

std::filesystem::path mask_defaults() {
  return std::filesystem::path(FLATNET_SOURCE_DIR) / "configs" / "mask_defaults.yaml";
}

WienerCamera wiener_camera(const Config& c) {
  WienerCamera cam;
  cam.rows = c.integer("camera.rows");
  cam.cols = c.integer("camera.cols");
  cam.scene = c.integer("camera.scene");
  cam.noise_sigma = c.num("camera.noise_sigma");
  cam.photons = c.num("camera.photons");
  require(cam.noise_sigma > 0, "camera.noise_sigma", "must be positive, got " + c.str("camera.noise_sigma"));
  require(cam.scene <= cam.rows && cam.scene <= cam.cols, "camera.scene", "must fit in the sensor");
  return cam;
}

std::vector<std::filesystem::path> first(const std::vector<std::filesystem::path>& v, int64_t n) {
  return n <= 0 || n >= static_cast<int64_t>(v.size()) ? v : std::vector<std::filesystem::path>(v.begin(), v.begin() + n);
}

int mask_train(int argc, char** argv) {
  cxxopts::Options o("flatnet mask train", "Learn a rank-k amplitude mask end to end through Wiener deconvolution.");
  o.add_options()("config", "experiment config (configs/mask_rank1.yaml, ...)", cxxopts::value<std::string>())(
      "set", "override a setting (repeatable)", cxxopts::value<std::vector<std::string>>())(
      "out", "output folder", cxxopts::value<std::string>());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "mask train", "--out DIR is required");
  const auto sets = set_overrides(r);
  const auto c = Config::load(r.count("config") ? r["config"].as<std::string>() : "", sets, mask_defaults());
  MaskOptions mo;
  mo.elements = c.integer("mask.elements");
  mo.rank = c.integer("mask.rank");
  mo.upsample = c.integer("mask.upsample");
  mo.projection = c.str("mask.projection");
  mo.throughput = c.str("mask.throughput");
  mo.target = c.num("mask.target_throughput");
  mo.binary = c.flag("mask.binary");
  mo.init = c.str("mask.init");
  mo.seed = static_cast<uint64_t>(c.integer("train.seed"));
  const auto cam = wiener_camera(c);
  mo.rows = cam.rows, mo.cols = cam.cols;
  MaskTrainOptions to;
  to.iterations = c.integer("train.iterations");
  to.batch = c.integer("train.batch");
  to.optimizer = c.str("train.optimizer");
  to.lr = c.num("train.lr");
  to.momentum = c.num("train.momentum");
  to.gamma_init = c.num("train.gamma_init");
  to.val_every = std::max<int64_t>(1, c.integer("train.val_every"));
  to.log_every = std::max<int64_t>(1, c.integer("train.log_every"));
  to.seed = mo.seed;
  to.out = r["out"].as<std::string>();
  require(to.gamma_init > 0, "train.gamma_init", "must be positive");
  MaskModel model(mo);  // validates rank, projection, throughput rule
  auto [train_imgs, val_imgs] = split_image_files(c.path("data.images"), c.num("data.val_fraction"), c.integer("data.split_seed"));
  std::cerr << "loading " << first(train_imgs, c.integer("data.train_limit")).size() << " training and "
            << first(val_imgs, c.integer("train.val_count")).size() << " validation photographs...\n";
  const auto train = load_luma_scenes(first(train_imgs, c.integer("data.train_limit")), cam.scene, 2);
  const auto val = load_luma_scenes(first(val_imgs, c.integer("train.val_count")), cam.scene, 2);
  std::filesystem::create_directories(to.out);
  write_text_atomically(to.out / "config.yaml", c.to_yaml());
  const auto s = train_mask(model, train, val, cam, to);
  std::cout << "rank " << mo.rank << " mask: validation PSNR " << std::fixed << std::setprecision(2) << s.val_psnr
            << " dB, throughput " << std::setprecision(3) << s.throughput << ", gamma " << std::scientific
            << std::setprecision(3) << s.gamma << std::defaultfloat << " after " << s.steps << " steps in "
            << format_duration(s.seconds) << "\nwrote " << (to.out / "mask.png").string() << ", vectors.mat, gamma.txt, log.csv, curve.png\n";
  return 0;
}

struct MaskScore {
  std::string name;
  double throughput = 0, gamma = 0, psnr = 0;
};

// gamma tuned on `tune`, PSNR on `test`.
MaskScore score_mask(const std::string& name, const torch::Tensor& window, const torch::Tensor& tune,
                     const torch::Tensor& test, const WienerCamera& cam) {
  MaskScore s{name, throughput(window), 0, 0};
  s.gamma = tune_gamma(window, tune, cam, 777);
  s.psnr = mask_psnr(window, s.gamma, test, cam, 4242);
  return s;
}

int mask_eval(int argc, char** argv) {
  cxxopts::Options o("flatnet mask eval", "Throughput, tuned gamma and mean PSNR of a mask under the Wiener protocol.");
  o.add_options()("mask", "mask.png (16-bit, 65535 = transparent), mls or m02", cxxopts::value<std::string>())(
      "images", "photographs: gamma is tuned on the first quarter, PSNR measured on the rest", cxxopts::value<std::string>())(
      "noise", "Gaussian noise sigma", cxxopts::value<double>()->default_value("3e-4"))(
      "count", "use at most this many photographs (0: all)", cxxopts::value<int>()->default_value("0"));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("mask") && r.count("images"), "mask eval", "--mask and --images are required");
  WienerCamera cam;
  cam.noise_sigma = r["noise"].as<double>();
  require(cam.noise_sigma > 0, "--noise", "must be positive");
  const auto window = load_mask_window(r["mask"].as<std::string>(), cam);
  require(window.min().item<double>() >= 0 && window.max().item<double>() <= 1, r["mask"].as<std::string>(),
          "transmittance outside [0, 1]");
  const auto images = first(list_images(r["images"].as<std::string>(), kImageExtensions), r["count"].as<int>());
  require(images.size() >= 2, r["images"].as<std::string>(), "needs at least 2 readable images");
  const auto scenes = load_luma_scenes(images, cam.scene, 2);
  const int64_t n_tune = std::max<int64_t>(1, scenes.size(0) / 4);
  const auto s = score_mask(r["mask"].as<std::string>(), window, scenes.slice(0, 0, n_tune), scenes.slice(0, n_tune), cam);
  std::cout << "mask " << s.name << ": throughput " << std::setprecision(4) << s.throughput << ", gamma "
            << std::scientific << std::setprecision(3) << s.gamma << std::defaultfloat << " (tuned on " << n_tune
            << " images), PSNR " << std::fixed << std::setprecision(2) << s.psnr << " dB on " << scenes.size(0) - n_tune
            << " images at sigma " << std::scientific << std::setprecision(1) << cam.noise_sigma << "\n";
  return 0;
}

// Separable model of a rank-1 mask: PhiL/PhiR from per-axis codes (4 sensor pixels per element,
// one sensor pixel of shadow shift per scene pixel), scaled to the convolution model's DC gain.
struct SeparableStats {
  double cond_l = 0, cond_r = 0, tik_psnr = 0, lambda = 0;
  torch::Tensor sv_l;
};

SeparableStats separable_stats(const std::vector<double>& code_u, const std::vector<double>& code_v,
                               const torch::Tensor& tune, const torch::Tensor& test, const WienerCamera& cam) {
  MaskGeometry g;
  g.feature_um = 4, g.pixel_pitch_um = 1, g.shift_features_per_pixel = 0.25, g.scene_pixels = cam.scene;
  g.sensor_pixels = cam.rows;
  const auto L = toeplitz_phi(code_u, g).to(torch::kFloat32) / (0.5 * cam.rows);
  g.sensor_pixels = cam.cols;
  const auto R = toeplitz_phi(code_v, g).to(torch::kFloat32) / (0.5 * cam.cols);
  auto [UL, sL, VLt] = torch::linalg::svd(L, false, c10::nullopt);
  auto [UR, sR, VRt] = torch::linalg::svd(R, false, c10::nullopt);
  SeparableStats st;
  st.cond_l = (sL.max() / sL.min()).item<double>();
  st.cond_r = (sR.max() / sR.min()).item<double>();
  st.sv_l = sL;
  const auto s = torch::outer(sL, sR);
  auto run = [&](const torch::Tensor& X, double lambda, uint64_t seed) {
    auto gen = at::detail::createCPUGenerator(seed);
    auto Y = torch::matmul(L, torch::matmul(X, R.t()));
    Y = Y + cam.noise_sigma * at::randn(Y.sizes(), gen);
    const auto core = torch::matmul(UL.t(), torch::matmul(Y, UR)) * (s / (s * s + lambda));
    const auto rec = torch::matmul(VLt.t(), torch::matmul(core, VRt)).clamp(0, 1);
    return (-10.0 * torch::log10((rec - X).pow(2).mean({1, 2}).clamp_min(1e-12))).mean().item<double>();
  };
  double best = -1e9;
  for (double lg = -10; lg <= -1; lg += 0.5) {
    const double p = run(tune, std::pow(10.0, lg), 1);
    if (p > best) best = p, st.lambda = std::pow(10.0, lg);
  }
  st.tik_psnr = run(test, st.lambda, 2);
  return st;
}

std::vector<double> normalised(const torch::Tensor& v) {
  const auto t = v.to(torch::kFloat64);
  const auto n = (t - t.min()) / (t.max() - t.min() + 1e-12);
  return std::vector<double>(n.data_ptr<double>(), n.data_ptr<double>() + n.numel());
}

int mask_report(int argc, char** argv) {
  cxxopts::Options o("flatnet mask report", "Compare learned masks with MLS and the 02 mask: table, noise sweep, figures.");
  o.add_options()("masks", "folders written by `flatnet mask train` (comma-separated)", cxxopts::value<std::vector<std::string>>())(
      "images", "photographs; the held-out split (as training's) is used", cxxopts::value<std::string>())(
      "out", "folder for report.md, masks.png, sweep.png, spectra.png", cxxopts::value<std::string>())(
      "noise", "noise sigma of the main table", cxxopts::value<double>()->default_value("3e-4"))(
      "tune-count", "held-out photographs used to tune gamma", cxxopts::value<int>()->default_value("50"))(
      "count", "held-out photographs scored after those (0: the rest)", cxxopts::value<int>()->default_value("0"));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("masks") && r.count("images") && r.count("out"), "mask report", "--masks, --images and --out are required");
  const std::filesystem::path out = r["out"].as<std::string>();
  WienerCamera cam;
  cam.noise_sigma = r["noise"].as<double>();
  const auto held_out = split_image_files(r["images"].as<std::string>(), 0.1, 1).second;
  const int64_t n_tune = r["tune-count"].as<int>();
  require(static_cast<int64_t>(held_out.size()) > n_tune, r["images"].as<std::string>(), "too few held-out photographs");
  const auto scenes = load_luma_scenes(held_out, cam.scene, 2);
  const auto tune = scenes.slice(0, 0, n_tune);
  const auto test = r["count"].as<int>() > 0 ? scenes.slice(0, n_tune, n_tune + r["count"].as<int>()) : scenes.slice(0, n_tune);

  // Masks: baselines, then each learned one.
  std::vector<std::pair<std::string, torch::Tensor>> masks = {{"MLS", load_mask_window("mls", cam)},
                                                              {"02 (FlatNet)", load_mask_window("m02", cam)}};
  std::vector<std::pair<std::string, std::filesystem::path>> learned;
  for (const auto& d : r["masks"].as<std::vector<std::string>>()) {
    const std::filesystem::path dir(d);
    masks.emplace_back("learned " + dir.filename().string(), load_mask_window((dir / "mask.png").string(), cam));
    learned.emplace_back(masks.back().first, dir);
  }
  std::ostringstream md;
  md << "# Learned masks vs MLS and FlatNet's 02 mask\n\nProtocol: 511-element masks, 4x4 sensor pixels per element, "
        "centred 500x620 PSF, 256x256 luma scenes centred in the canvas, circular convolution, Gaussian noise, Wiener "
        "deconvolution with gamma tuned per mask (and per noise level) on "
     << n_tune << " held-out photographs; PSNR on " << test.size(0)
     << " further held-out photographs (`flatnet mask report`).\n\n";
  MarkdownTable main_table{{"mask", "throughput", "gamma", "PSNR dB (sigma " + scientific(cam.noise_sigma, 1) + ")"}, {}};
  std::vector<MaskScore> scores;
  for (const auto& [name, w] : masks) {
    scores.push_back(score_mask(name, w, tune, test, cam));
    const auto& s = scores.back();
    main_table.add({name, fixed(s.throughput, 3), scientific(s.gamma, 2), fixed(s.psnr, 2)});
    std::cerr << name << ": " << s.psnr << " dB\n";
  }
  md << main_table.markdown() << "\nThe 02 mask passes about 2% of the light, so it is compared apart (not at equal light). Its PSF "
        "covers only 124x124 pixels, so its deconvolution is well conditioned; with noise that does not depend "
        "on the signal, as in this protocol, that outweighs the light it loses.\n\n"
        "## Noise sweep (PSNR dB; gamma re-tuned at each level)\n\n";
  const std::vector<double> sigmas = {1e-4, 3e-4, 1e-3, 3e-3};
  std::vector<Series> sweep;
  MarkdownTable sweep_table{{"sigma"}, {}};
  for (const auto& [name, w] : masks) sweep_table.header.push_back(name), sweep.push_back({name, {}, {}});
  for (const double sg : sigmas) {
    WienerCamera c2 = cam;
    c2.noise_sigma = sg;
    std::vector<std::string> row{scientific(sg, 0)};
    for (size_t i = 0; i < masks.size(); ++i) {
      const auto s = score_mask(masks[i].first, masks[i].second, tune, test, c2);
      row.push_back(fixed(s.psnr, 2));
      sweep[i].x.push_back(sg);
      sweep[i].y.push_back(s.psnr);
    }
    sweep_table.add(row);
  }
  md << sweep_table.markdown();
  std::filesystem::create_directories(out);
  PlotOptions po;
  po.title = "PSNR vs noise (Wiener, gamma tuned per level)";
  po.xlabel = "noise sigma";
  po.ylabel = "PSNR dB";
  po.log_x = true;
  write_line_plot(out / "sweep.png", sweep, po);

  // Rank-1 masks on the separable FlatCam model.
  md << "\n## Rank-1 masks as separable FlatCam matrices\n\nPhiL (500x256) and PhiR (620x256) built from each "
        "axis's code (learned vectors scaled to [0,1]; MLS (m+1)/2), Tikhonov with lambda tuned the same way, sigma "
     << std::scientific << std::setprecision(1) << cam.noise_sigma
     << ". A learned rank-1 mask is sigmoid(u v^T + b), which is not separable, so its vectors are only an "
        "approximation of separable codes, and they were optimised for the Wiener pipeline, not for this model.\n\n";
  MarkdownTable separable_table{{"mask", "cond(PhiL)", "cond(PhiR)", "Tikhonov PSNR dB"}, {}};
  std::vector<Series> spectra;
  auto add_separable = [&](const std::string& name, const std::vector<double>& u, const std::vector<double>& v) {
    const auto st = separable_stats(u, v, tune, test, cam);
    separable_table.add({name, scientific(st.cond_l, 2), scientific(st.cond_r, 2), fixed(st.tik_psnr, 2)});
    Series s{name, {}, {}};
    const auto sv = (st.sv_l / st.sv_l.max()).to(torch::kFloat64);
    for (int64_t i = 0; i < sv.numel(); ++i) s.x.push_back(static_cast<double>(i)), s.y.push_back(std::log10(sv[i].item<double>() + 1e-12));
    spectra.push_back(s);
  };
  const auto code = mls(9);
  std::vector<double> mcode;
  for (int c : code) mcode.push_back((c + 1) / 2.0);
  add_separable("MLS", mcode, mcode);
  for (const auto& [name, dir] : learned) {
    MatReader vec(dir / "vectors.mat");
    const auto U = vec.read("U"), V = vec.read("V");
    if (U.size(1) != 1) continue;
    add_separable(name, normalised(U.select(1, 0)), normalised(V.select(1, 0)));
  }
  md << separable_table.markdown();
  PlotOptions sp;
  sp.title = "singular values of PhiL (log10 of s / s_max)";
  sp.xlabel = "index";
  sp.ylabel = "log10";
  write_line_plot(out / "spectra.png", spectra, sp);

  // Figure: each mask's window and its reconstruction of one held-out photograph.
  std::vector<std::string> labels;
  std::vector<torch::Tensor> row_masks, row_recs;
  const auto x = test.slice(0, 0, 1);
  for (size_t i = 0; i < masks.size(); ++i) {
    labels.push_back(masks[i].first.substr(0, 22));
    row_masks.push_back(masks[i].second.unsqueeze(0).repeat({3, 1, 1}));
    const auto P = psf_spectrum(masks[i].second);
    auto gen = at::detail::createCPUGenerator(99);
    const auto rec = wiener(capture(x, P, cam, gen), P, torch::tensor(scores[i].gamma), cam)[0].clamp(0, 1);
    row_recs.push_back(rec.unsqueeze(0).repeat({3, 1, 1}));
  }
  labels.insert(labels.begin(), "truth");
  row_masks.insert(row_masks.begin(), torch::ones({3, cam.scene, cam.scene}));
  row_recs.insert(row_recs.begin(), x[0].unsqueeze(0).repeat({3, 1, 1}));
  write_contact_sheet(out / "masks.png", labels, {"mask window", "reconstruction"}, {row_masks, row_recs});
  md << "\n![masks and reconstructions](masks.png)\n\n![noise sweep](sweep.png)\n\n![PhiL spectra](spectra.png)\n";
  write_text_atomically(out / "report.md", md.str());
  std::cout << md.str();
  return 0;
}

// flatnet mask separable: learns the code pair of the separable camera through Tikhonov.
int mask_separable(int argc, char** argv) {
  cxxopts::Options o("flatnet mask separable",
                     "Learn a separable FlatCam's codes end to end: codes -> PhiL/PhiR -> noisy capture -> Tikhonov.");
  o.add_options()("images", "photographs (the training side of simulate's split is used)", cxxopts::value<std::string>())(
      "out", "folder for codes.mat, lambda.txt, log.csv, curve.png", cxxopts::value<std::string>())(
      "init", "mls (models/camera/codes_mls.mat), random, or a codes .mat", cxxopts::value<std::string>()->default_value("mls"))(
      "binary", "sign(u), sign(v) forward, straight-through gradients (a fabricable 0/1 mask)")(
      "iterations", "steps", cxxopts::value<int64_t>()->default_value("1000"))(
      "batch", "scenes per step", cxxopts::value<int64_t>()->default_value("8"))(
      "lr", "Adam learning rate", cxxopts::value<double>()->default_value("0.02"))(
      "lambda", "initial Tikhonov regulariser", cxxopts::value<double>()->default_value("1e-4"))(
      "train-limit", "training photographs loaded (0: all)", cxxopts::value<int64_t>()->default_value("400"))(
      "val-count", "held-out photographs for validation", cxxopts::value<int64_t>()->default_value("32"))(
      "seed", "seed", cxxopts::value<uint64_t>()->default_value("0"));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "mask separable", "--images DIR and --out DIR are required");
  SeparableTrainOptions opt;
  opt.images = r["images"].as<std::string>();
  opt.out = r["out"].as<std::string>();
  require(!std::filesystem::exists(opt.out / "codes.mat"), opt.out, "already holds learned codes; choose another --out");
  const auto init = r["init"].as<std::string>();
  if (init == "mls") opt.init_codes = std::filesystem::path(FLATNET_SOURCE_DIR) / "models" / "camera" / "codes_mls.mat";
  else if (init != "random") opt.init_codes = init;
  opt.binary = r.count("binary") > 0;
  opt.iterations = r["iterations"].as<int64_t>();
  opt.batch = r["batch"].as<int64_t>();
  opt.lr = r["lr"].as<double>();
  opt.lambda_init = r["lambda"].as<double>();
  opt.train_limit = r["train-limit"].as<int64_t>();
  opt.val_count = r["val-count"].as<int64_t>();
  opt.seed = r["seed"].as<uint64_t>();
  require(opt.iterations >= 1 && opt.iterations <= 1000000, "--iterations", "1 to 1e6");
  require(opt.batch >= 1 && opt.batch <= 256, "--batch", "1 to 256");
  require(std::isfinite(opt.lr) && opt.lr > 0 && opt.lr <= 10, "--lr", "a positive rate");
  require(std::isfinite(opt.lambda_init) && opt.lambda_init > 0, "--lambda", "a positive regulariser");
  require(opt.val_count >= 1, "--val-count", "at least 1");
  watch_interrupts();
  const auto s = train_separable_codes(opt);
  std::cout << "separable codes: " << s.steps << " steps in " << format_duration(s.seconds) << "; validation PSNR "
            << s.val_psnr_start << " -> " << s.val_psnr << " dB (Tikhonov, linear light), lambda " << s.lambda
            << ", throughput " << s.throughput << "; wrote " << (opt.out / "codes.mat").string() << "\n";
  return interrupted() ? 130 : 0;
}

// flatnet mask camera: the reference camera with another separable code pair.
int mask_camera(int argc, char** argv) {
  cxxopts::Options o("flatnet mask camera",
                     "Build the reference camera with a separable code pair: rig.mat, calib.mat (with estimation error) "
                     "and camera.yaml, for simulate, calibrate, recon and train.");
  o.add_options()("codes", ".mat with code_rows and code_cols (vectors, values in [-1, 1]); models/camera/codes_mls.mat is MLS",
                  cxxopts::value<std::string>())("out", "folder to write", cxxopts::value<std::string>())(
      "calib-error", "relative (Frobenius) error of the calibration, as a real one has", cxxopts::value<double>()->default_value("0.03"))(
      "seed", "seed of that error", cxxopts::value<uint64_t>()->default_value("0"))(
      "centring", "plane, or level (for models that read the light level, as the shipped ones)",
      cxxopts::value<std::string>()->default_value("plane"))(
      "force", "replace the files of an existing camera in --out");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("codes") && r.count("out"), "mask camera", "--codes FILE and --out DIR are required");
  const std::filesystem::path codes_path = r["codes"].as<std::string>(), out = r["out"].as<std::string>();
  const double error = r["calib-error"].as<double>();
  require(std::isfinite(error) && error >= 0 && error <= 1, "--calib-error", "0 to 1 (0.03: 3 %)");
  MatReader codes(codes_path);
  auto vector_of = [&](const char* name) {
    const auto t = codes.read(name);
    require(t.dim() <= 2 && t.numel() >= 2 && t.numel() == t.size(0) * (t.dim() == 2 ? t.size(1) : 1) &&
                (t.dim() < 2 || t.size(0) == 1 || t.size(1) == 1),
            codes_path, std::string("variable '") + name + "' must be a vector");
    const auto v = t.flatten();
    require(torch::isfinite(v).all().item<bool>() && v.abs().max().item<double>() <= 1.0 + 1e-9, codes_path,
            std::string("variable '") + name + "' must hold values in [-1, 1]");
    return v;
  };
  const auto u = vector_of("code_rows"), v = vector_of("code_cols");
  std::filesystem::create_directories(out);
  for (const char* f : {"rig.mat", "calib.mat", "camera.yaml"}) require_new_output(out / f, r.count("force") > 0, {codes_path});
  const auto rig = separable_rig(u, v);
  auto camera = load_camera_config(default_camera_path());
  camera.name = out.filename().string();
  camera.raw.centring = parse_centring(r["centring"].as<std::string>(), "--centring");
  const auto calib = calibration_of(rig, camera.raw.crop, error, r["seed"].as<uint64_t>());
  save_rig(out / "rig.mat", rig);
  save_calibration(out / "calib.mat", calib);
  write_text_atomically(out / "camera.yaml",
                        "# The reference camera with the codes of " + codes_path.string() + " (`flatnet mask camera`)\n" +
                            camera_geometry_yaml(camera) + "calibration: calib.mat\nrig: rig.mat\n");
  std::cout << "camera with codes " << codes_path.string() << " (" << u.numel() << " x " << v.numel() << " features, mean "
            << "transmittance " << (1 + u.mean().item<double>() * v.mean().item<double>()) / 2 << "): "
            << (out / "camera.yaml").string() << ", rig.mat, calib.mat (" << error * 100 << " % error)\n";
  return 0;
}

}  // namespace

int mask(int argc, char** argv) {
  const std::string usage =
      "usage: flatnet mask train|eval|report|camera|separable [options]  ('flatnet mask <sub> --help' lists them)";
  if (argc < 2) throw Error(usage);
  const std::string sub = argv[1];
  if (sub == "train") return mask_train(argc - 1, argv + 1);
  if (sub == "eval") return mask_eval(argc - 1, argv + 1);
  if (sub == "report") return mask_report(argc - 1, argv + 1);
  if (sub == "camera") return mask_camera(argc - 1, argv + 1);
  if (sub == "separable") return mask_separable(argc - 1, argv + 1);
  if (sub == "-h" || sub == "--help") {
    std::cout << usage << "\n";
    return 0;
  }
  throw Error("mask: unknown subcommand '" + sub + "'; " + usage);
}

}  // namespace flatnet::cli
