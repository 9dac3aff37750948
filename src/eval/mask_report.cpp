#include "eval/mask_report.hpp"

#include <ATen/Parallel.h>

#include <cmath>
#include <iomanip>
#include <iostream>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/metrics.hpp"
#include "eval/plot.hpp"
#include "eval/tables.hpp"
#include "io/mat.hpp"
#include "io/raw.hpp"
#include "optics/codes.hpp"
#include "optics/mask.hpp"
#include "optics/simulator.hpp"
#include "io/image.hpp"
#include "recon/tikhonov.hpp"
#include "eval/mask_score.hpp"

namespace flatnet {

// ---- 2. The separable FlatCam ------------------------------------------------------------------

namespace {

// The rig as `flatnet mask camera` writes it and `load_rig` reads it back (float32 matrices).
Rig camera_rig(const CodePair& codes, const SeparableCameraOptions& camera) {
  Rig rig = separable_rig(codes.rows, codes.cols, camera);
  rig.phil = rig.phil.detach().to(torch::kFloat32).contiguous();
  rig.phir = rig.phir.detach().to(torch::kFloat32).contiguous();
  rig.gain = rig.gain.detach().to(torch::kFloat32);
  rig.vig_rows = rig.vig_rows.detach().to(torch::kFloat32);
  rig.vig_cols = rig.vig_cols.detach().to(torch::kFloat32);
  return rig;
}

// One held-out capture as `flatnet simulate --seed S` makes it for this photograph: the noise
// generator is seeded by the capture's name, so every camera sees the same noise draw.
torch::Tensor capture_unit(const Rig& rig, const torch::Tensor& scene, const std::string& name, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(stable_hash(name, seed));
  return simulate_raw(rig, scene, true, gen).to(torch::kFloat32) / 65535.0f;  // {2h,2w} in [0,1]
}

std::string capture_name(const std::filesystem::path& photo) { return photo.stem().string() + ".png"; }

torch::Tensor as_8bit(const torch::Tensor& image) { return torch::round(image.clamp(0, 1) * 255.0f) / 255.0f; }

// Share of a code's AC power (real FFT, DC excluded) in the lowest eighth of its frequencies.
double low_frequency_share(const torch::Tensor& code) {
  const auto power = torch::fft::rfft(code.to(torch::kFloat64) - code.mean()).abs().pow(2);  // {K/2+1}
  const int64_t ac = power.size(0) - 1, low = (ac + 7) / 8;
  return (power.slice(0, 1, 1 + low).sum() / power.slice(0, 1).sum().clamp_min(1e-300)).item<double>();
}

double condition_number(const torch::Tensor& m) {
  const auto s = torch::linalg_svdvals(m.to(torch::kFloat64));
  return (s.max() / s.min()).item<double>();
}

// Centred planes of every held-out capture through `rig`: {n,4,h,w} (what Tikhonov reads).
torch::Tensor centred_captures(const Rig& rig, const torch::Tensor& scenes, const std::vector<std::string>& names,
                               const SeparableReportOptions& opt, Progress& progress) {
  const int64_t n = scenes.size(0);
  auto planes = torch::empty({n, 4, opt.geometry.crop[2], opt.geometry.crop[3]});
  at::parallel_for(0, n, 1, [&](int64_t begin, int64_t end) {
    c10::InferenceMode guard;
    for (int64_t i = begin; i < end; ++i) {
      const auto raw = capture_unit(rig, scenes[i], names[i], opt.noise_seed);
      planes[i].copy_(without_level(preprocess_raw(raw, opt.geometry), opt.geometry.centring));
      progress.tick();
    }
  });
  return planes;
}

struct Scored {
  std::vector<double> psnr, ssim;  // per photograph
};

// Tikhonov reconstructions of captures [begin, end), as 8-bit sRGB images scored against the scenes.
Scored score_tikhonov(const Tikhonov& tik, const torch::Tensor& planes, const torch::Tensor& scenes, int64_t begin,
                      int64_t end, bool with_ssim) {
  Scored s;
  for (int64_t b = begin; b < end; b += 8) {
    const auto X = tik(planes.slice(0, b, std::min(end, b + 8)));  // {B,4,N,N}
    for (int64_t i = 0; i < X.size(0); ++i) {
      const auto image = as_8bit(planes_to_srgb(X[i]));
      s.psnr.push_back(psnr(image, scenes[b + i]));
      if (with_ssim) s.ssim.push_back(ssim(image, scenes[b + i]));
    }
  }
  return s;
}

double mean_of(const std::vector<double>& v) {
  double total = 0;
  for (double x : v) total += x;
  return v.empty() ? std::nan("") : total / static_cast<double>(v.size());
}

}  // namespace

std::vector<SeparableScore> score_separable_cameras(const std::vector<SeparableCandidate>& candidates,
                                                    const std::vector<std::filesystem::path>& held_out,
                                                    const SeparableReportOptions& opt) {
  c10::InferenceMode guard;
  const int64_t n_all = static_cast<int64_t>(held_out.size());
  require(opt.tune_count >= 1 && n_all > opt.tune_count, "mask report",
          "the separable comparison needs more than " + std::to_string(opt.tune_count) + " held-out photographs, got " +
              std::to_string(n_all));
  require(!opt.lambdas.empty() && !opt.light.empty(), "mask report", "needs at least one lambda and one light level");
  const int64_t n = opt.count > 0 ? std::min(n_all, opt.tune_count + opt.count) : n_all;
  const int64_t tune = opt.tune_count;
  std::vector<torch::Tensor> scene_list;
  std::vector<std::string> names;
  for (int64_t i = 0; i < n; ++i)
    scene_list.push_back(display_scene(held_out[i], opt.camera.scene)), names.push_back(capture_name(held_out[i]));
  const auto scenes = torch::stack(scene_list);  // {n,3,N,N} sRGB as the display shows them

  std::vector<SeparableScore> scores;
  for (const auto& c : candidates) {
    SeparableScore s;
    s.name = c.name;
    s.origin = c.origin;
    s.throughput = c.codes.throughput();
    s.scored = n - tune;
    const Rig rig = camera_rig(c.codes, opt.camera);
    const auto calib = calibration_of(rig, opt.geometry.crop, opt.calib_error, opt.calib_seed);
    s.cond_p = condition_number(calib.P[1]);
    s.cond_q = condition_number(calib.Q[1]);
    s.low_share_rows = low_frequency_share(c.codes.rows);
    s.low_share_cols = low_frequency_share(c.codes.cols);
    Tikhonov tik(calib, opt.lambdas.front());
    for (size_t level = 0; level < opt.light.size(); ++level) {
      Rig lit = rig;
      lit.full_well = rig.full_well * opt.light[level];  // fewer photons per full scale: more shot noise
      Progress progress(c.name + " light " + fixed(opt.light[level], 3), n, opt.progress);
      const auto planes = centred_captures(lit, scenes, names, opt, progress);
      progress.finish();
      // lambda: the best mean PSNR on the tuning photographs (at full light, every photograph is
      // reconstructed at every lambda, for the sweep table).
      double best = -1e9, best_lambda = opt.lambdas.front();
      for (double lambda : opt.lambdas) {
        tik.set_lambda(lambda);
        const auto sc = score_tikhonov(tik, planes, scenes, 0, level == 0 ? n : tune, false);
        const double tuned = mean_of(std::vector<double>(sc.psnr.begin(), sc.psnr.begin() + tune));
        if (level == 0) s.lambda_sweep_psnr.push_back(mean_of(sc.psnr));
        if (tuned > best) best = tuned, best_lambda = lambda;
      }
      tik.set_lambda(best_lambda);
      const auto scored = score_tikhonov(tik, planes, scenes, tune, n, true);
      s.lambda.push_back(best_lambda), s.psnr.push_back(mean_of(scored.psnr)), s.ssim.push_back(mean_of(scored.ssim));
    }
    // FlatNet: at the camera's light, on the scored photographs, preprocessed as the model was trained.
    // The captures are simulated again (seeded by name: the same draws) rather than kept from the
    // Tikhonov pass, which would hold ~1 GB of raw frames for a few seconds of simulation.
    if (c.flatnet) {
      const auto& model = *c.flatnet;
      require(model.geometry.raw_height == opt.geometry.raw_height &&
                  model.geometry.raw_width == opt.geometry.raw_width && model.geometry.crop == opt.geometry.crop,
              model.label, "was trained for another sensor crop than the reference camera's");
      Scored fs;
      Progress progress(c.name + " FlatNet", n - tune, opt.progress);
      for (int64_t b = tune; b < n; b += 4) {
        std::vector<torch::Tensor> batch;
        for (int64_t i = b; i < std::min(n, b + 4); ++i)
          batch.push_back(preprocess_raw(capture_unit(rig, scenes[i], names[i], opt.noise_seed), model.geometry));
        const auto images = model.forward(torch::stack(batch));  // {B,3,N,N}
        for (int64_t i = 0; i < images.size(0); ++i) {
          const auto image = as_8bit(images[i].to(torch::kFloat32));
          fs.psnr.push_back(psnr(image, scenes[b + i]));
          fs.ssim.push_back(ssim(image, scenes[b + i]));
          progress.tick();
        }
      }
      progress.finish();
      s.flatnet_label = model.label;
      s.flatnet_psnr = mean_of(fs.psnr);
      s.flatnet_ssim = mean_of(fs.ssim);
    }
    if (opt.progress)
      std::cerr << c.name << ": Tikhonov " << fixed(s.psnr[0], 2) << " dB / " << fixed(s.ssim[0], 3) << " (lambda "
                << scientific(s.lambda[0], 0) << ")\n";
    scores.push_back(s);
  }
  return scores;
}

std::string separable_section(const std::vector<SeparableScore>& scores, const SeparableReportOptions& opt) {
  std::ostringstream md;
  const double full_well = opt.camera.full_well;
  md << "## The separable FlatCam: each code pair built into the reference camera\n\n"
        "Each pair of codes u (rows), v (columns) becomes the reference camera with the mask (1 + u v^T) / 2 (`flatnet "
        "mask camera`: the same sensor, sub-pixel sampling, blur, vignetting and gains; a calibration with "
     << fixed(100 * opt.calib_error, 0)
     << " % error). The held-out photographs are captured through each rig as `flatnet simulate --seed "
     << opt.noise_seed
     << " --only val` captures them (the same photographs and noise draws for every camera; Poisson and read noise, "
        "10-bit ADC), reconstructed by Tikhonov from the calibration, and scored in sRGB, colour, 8-bit, as `flatnet "
        "eval` scores. Lambda is tuned per camera and light level on the first "
     << opt.tune_count << " held-out photographs; PSNR / SSIM are on the " << scores.front().scored
     << " after them. FlatNet: a model trained on that camera (`flatnet train` with `data.camera` set to it), on the "
        "same captures.\n\n";
  MarkdownTable main{{"codes", "throughput", "Tikhonov lambda", "Tikhonov PSNR / SSIM",
                      "vs " + scores.front().name + " (dB)", "FlatNet PSNR / SSIM"},
                     {}};
  for (const auto& s : scores)
    main.add(
        {s.name, fixed(s.throughput, 3), scientific(s.lambda[0], 0), fixed(s.psnr[0], 2) + " / " + fixed(s.ssim[0], 3),
         (s.psnr[0] >= scores.front().psnr[0] ? "+" : "") + fixed(s.psnr[0] - scores.front().psnr[0], 2),
         std::isnan(s.flatnet_psnr) ? "not trained" : fixed(s.flatnet_psnr, 2) + " / " + fixed(s.flatnet_ssim, 3)});
  md << main.markdown() << "\n";
  for (const auto& s : scores)
    md << "- " << s.name << ": " << s.origin << (s.flatnet_label.empty() ? "" : "; FlatNet " + s.flatnet_label) << "\n";

  md << "\n### Tikhonov PSNR at each lambda (every held-out photograph, the camera's light)\n\n";
  MarkdownTable sweep{{"codes"}, {}};
  for (double l : opt.lambdas) sweep.header.push_back(scientific(l, 0));
  for (const auto& s : scores) {
    std::vector<std::string> row{s.name};
    for (double p : s.lambda_sweep_psnr) row.push_back(fixed(p, 2));
    sweep.add(row);
  }
  md << sweep.markdown();

  md << "\n### Light sweep (Tikhonov PSNR dB; lambda re-tuned at each level)\n\nFewer photons per full scale "
        "(the camera has "
     << fixed(full_well, 0) << "): more shot noise relative to the signal, the same scenes and read noise.\n\n";
  MarkdownTable light{{"electrons at full scale"}, {}};
  for (const auto& s : scores) light.header.push_back(s.name);
  for (size_t level = 0; level < opt.light.size(); ++level) {
    std::vector<std::string> row{fixed(full_well * opt.light[level], 0)};
    for (const auto& s : scores) row.push_back(fixed(s.psnr[level], 2) + " (" + scientific(s.lambda[level], 0) + ")");
    light.add(row);
  }
  md << light.markdown();

  md << "\n### What the codes change\n\n";
  MarkdownTable codes{{"codes", "AC power in the lowest eighth of frequencies (u / v)", "cond(P1gb) / cond(Q1gb)"}, {}};
  for (const auto& s : scores)
    codes.add({s.name, fixed(s.low_share_rows, 2) + " / " + fixed(s.low_share_cols, 2),
               fixed(s.cond_p, 0) + " / " + fixed(s.cond_q, 0)});
  md << codes.markdown()
     << "\nA flat spectrum (MLS: about an eighth of the power in an eighth of the frequencies) conditions the matrices "
        "best; codes that put their power into the "
        "low frequencies, where natural scenes keep most of their energy and the sensor's blur and pixel integration "
        "lose least, give those modes the light, at the price of a worse condition number that Tikhonov's larger "
        "lambda "
        "absorbs.\n";
  return md.str();
}

MappedCodes codes_from_wiener_mask(const std::filesystem::path& dir) {
  MatReader vectors(dir / "vectors.mat");
  const auto U = vectors.read("U"), V = vectors.read("V");
  require(U.dim() == 2 && V.dim() == 2 && U.size(1) == 1 && V.size(1) == 1, dir / "vectors.mat",
          "is not a rank-1 mask's (U and V must be Kx1)");
  MappedCodes m;
  m.codes.rows = torch::where(U.flatten() >= 0, 1.0, -1.0).to(torch::kFloat64);
  m.codes.cols = torch::where(V.flatten() >= 0, 1.0, -1.0).to(torch::kFloat64);
  WienerCamera cam;
  const auto learned = load_mask_window((dir / "mask.png").string(), cam) > 0.5;  // {rows, cols}
  const auto mask = (1 + torch::outer(m.codes.rows, m.codes.cols)) / 2;           // {K,K}
  const auto mapped = mask_window(mask.to(torch::kFloat32), 4, cam.rows, cam.cols) > 0.5;
  m.agreement = (learned == mapped).to(torch::kFloat64).mean().item<double>();
  return m;
}

// ---- 1. The Wiener protocol, and the report ----------------------------------------------------

namespace {

// PSNR against a logarithmic x axis (both sweeps).
PlotOptions psnr_plot(const std::string& title, const std::string& xlabel) {
  PlotOptions p;
  p.title = title;
  p.xlabel = xlabel;
  p.ylabel = "PSNR dB";
  p.log_x = true;
  return p;
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

// The thesis's protocol: table, noise sweep, figures (sweep.png, masks.png).
std::string wiener_sections(const MaskReportOptions& opt, const std::vector<std::filesystem::path>& held_out) {
  WienerCamera cam;
  cam.noise_sigma = opt.noise;
  const int64_t n_tune = opt.tune_count;
  const auto scenes = load_luma_scenes(held_out, cam.scene, 2);
  const auto tune = scenes.slice(0, 0, n_tune);
  const auto test = opt.count > 0 ? scenes.slice(0, n_tune, n_tune + opt.count) : scenes.slice(0, n_tune);

  // Masks: baselines, then each learned one.
  std::vector<std::pair<std::string, torch::Tensor>> masks = {{"MLS", load_mask_window("mls", cam)},
                                                              {"02 (FlatNet)", load_mask_window("m02", cam)}};
  for (const auto& dir : opt.mask_dirs)
    masks.emplace_back("learned " + dir.filename().string(), load_mask_window((dir / "mask.png").string(), cam));
  std::ostringstream md;
  md << "# Learned masks vs MLS and FlatNet's 02 mask\n\nProtocol: 511-element masks, 4x4 sensor pixels per element, "
        "centred 500x620 PSF, 256x256 luma scenes centred in the canvas, circular convolution, Gaussian noise, Wiener "
        "deconvolution with gamma tuned per mask (and per noise level) on "
     << n_tune << " held-out photographs; PSNR on " << test.size(0)
     << " further held-out photographs (`flatnet mask report`).\n\n";
  MarkdownTable main_table{{"mask", "throughput", "gamma", "PSNR dB (sigma " + scientific(cam.noise_sigma, 1) + ")"},
                           {}};
  std::vector<MaskScore> scores;
  for (const auto& [name, w] : masks) {
    scores.push_back(score_mask(name, w, tune, test, cam));
    const auto& s = scores.back();
    main_table.add({name, fixed(s.throughput, 3), scientific(s.gamma, 2), fixed(s.psnr, 2)});
    std::cerr << name << ": " << s.psnr << " dB\n";
  }
  md << main_table.markdown()
     << "\nThe 02 mask passes about 2% of the light, so it is compared apart (not at equal light). Its PSF "
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
  std::filesystem::create_directories(opt.out);
  write_line_plot(opt.out / "sweep.png", sweep,
                  psnr_plot("PSNR vs noise (Wiener, gamma tuned per level)", "noise sigma"));

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
  write_contact_sheet(opt.out / "masks.png", labels, {"mask window", "reconstruction"}, {row_masks, row_recs});
  md << "\n![masks and reconstructions](masks.png)\n\n![noise sweep](sweep.png)\n";

  return md.str();
}

}  // namespace

std::string write_mask_report(const MaskReportOptions& opt) {
  require(opt.wiener || !opt.separable.empty(), "mask report",
          "has nothing to report (no Wiener sections, no code pairs)");
  {  // its figures are PNGs: written among the photographs, they would become photographs next time
    std::error_code a, b;
    require_option(std::filesystem::weakly_canonical(opt.out, a) != std::filesystem::weakly_canonical(opt.images, b),
                   "mask_report.out",
                   "is the photographs folder; the report's PNGs would join the photographs (choose another folder)");
  }
  require_option(std::isfinite(opt.noise) && opt.noise > 0, "mask_report.noise", "must be positive");
  const auto held_out = split_image_files(opt.images, 0.1, 1).second;
  require(opt.tune_count >= 1 && static_cast<int64_t>(held_out.size()) > opt.tune_count, opt.images,
          "too few held-out photographs (" + std::to_string(held_out.size()) + ") for " +
              std::to_string(opt.tune_count) + " to tune");
  std::ostringstream md;
  std::filesystem::create_directories(opt.out);
  if (opt.wiener) md << wiener_sections(opt, held_out);
  if (!opt.separable.empty()) {
    const auto sep = score_separable_cameras(opt.separable, held_out, opt.separable_options);
    md << (opt.wiener ? "\n" : "# Separable cameras from code pairs\n\n")
       << separable_section(sep, opt.separable_options);
    std::vector<Series> light;
    for (const auto& s : sep) {
      light.push_back({s.name, {}, s.psnr});
      for (double l : opt.separable_options.light) light.back().x.push_back(l * opt.separable_options.camera.full_well);
    }
    write_line_plot(opt.out / "separable_sweep.png", light,
                    psnr_plot("separable camera: Tikhonov PSNR vs light", "electrons at full scale"));
    md << "\n![separable cameras: light sweep](separable_sweep.png)\n";
  }
  write_text_atomically(opt.out / "report.md", md.str());
  return md.str();
}

}  // namespace flatnet
