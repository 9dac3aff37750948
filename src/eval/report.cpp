#include "eval/report.hpp"

#include <iomanip>
#include <nlohmann/json.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/metrics.hpp"
#include "eval/niqe.hpp"
#include "io/image.hpp"

namespace flatnet {

namespace {

struct Method {
  std::string name;
  std::filesystem::path dir;
};

// A folder of PNGs is one method; otherwise each subfolder holding PNGs is a method.
std::vector<Method> find_methods(const std::filesystem::path& out) {
  require(std::filesystem::is_directory(out), out, "reconstruction folder not found");
  std::vector<Method> methods;
  bool has_png = false;
  for (const auto& e : std::filesystem::directory_iterator(out))
    if (e.is_regular_file() && has_extension(e.path(), {".png"}) && e.path().filename() != "sheet.png") has_png = true;
  if (has_png) return {{out.filename().string(), out}};
  for (const auto& e : std::filesystem::directory_iterator(out))
    if (e.is_directory()) {
      bool any = false;
      for (const auto& f : std::filesystem::directory_iterator(e.path()))
        if (has_extension(f.path(), {".png"})) {
          any = true;
          break;
        }
      if (any) methods.push_back({e.path().filename().string(), e.path()});
    }
  std::sort(methods.begin(), methods.end(), [](const Method& a, const Method& b) { return a.name < b.name; });
  require(!methods.empty(), out, "no reconstructions (.png files, or subfolders of them) to evaluate");
  return methods;
}

// Mean and standard deviation of a column over the images where it is finite (NIQE of a flat image,
// a ratio to a truth without colour and the like are NaN and left out).
struct FiniteStats {
  double sum = 0, sq = 0;
  int64_t n = 0;
  void add(double v) {
    if (std::isfinite(v)) sum += v, sq += v * v, ++n;
  }
  double mean() const { return n > 0 ? sum / n : std::nan(""); }
  double sd() const { return n > 0 ? std::sqrt(std::max(0.0, sq / n - mean() * mean())) : std::nan(""); }
};

// The optional scorers: NIQE (a model file) and LPIPS (a backbone's weights).
struct Scorers {
  bool with_niqe = false, with_lpips = false;
  NiqeModel niqe;
  Lpips lpips{nullptr};
  std::string lpips_net;
};

Scorers load_scorers(const EvalOptions& opt) {
  Scorers s;
  s.with_niqe = !opt.niqe_model.empty();
  if (s.with_niqe) s.niqe = load_niqe(opt.niqe_model);
  s.with_lpips = !opt.lpips.empty();
  if (s.with_lpips) s.lpips = load_lpips(parse_lpips_backbone(opt.lpips), opt.lpips_files);
  s.lpips_net = opt.lpips;
  return s;
}

// The truth of `rec_path`'s scene at the reconstruction's size. Reconstructions at another resolution
// are compared with the truth resized; another shape (a raw capture, a crop) is a wrong folder, not a score.
torch::Tensor truth_for(const std::filesystem::path& gt_path, const std::filesystem::path& rec_path,
                        const torch::Tensor& rec) {
  const auto truth = read_rgb(gt_path);
  const double rec_aspect = double(rec.size(2)) / rec.size(1), gt_aspect = double(truth.size(2)) / truth.size(1);
  require(std::abs(rec_aspect / gt_aspect - 1) < 0.01, rec_path,
          "is " + std::to_string(rec.size(2)) + "x" + std::to_string(rec.size(1)) + ", its ground truth " +
              std::to_string(truth.size(2)) + "x" + std::to_string(truth.size(1)) +
              ": not a reconstruction of that scene (is " + option_key("eval.out") + " a folder of reconstructions?)");
  return resize(truth, rec.size(1), rec.size(2));
}

// The truth of one scene and the scores that depend on it alone.
struct Truth {
  torch::Tensor image;  // {3,H,W}
  double colour = 0, detail = 0;
};

// Every score of one reconstruction against its truth (a row of metrics.csv).
struct Scored {
  ImageScore image;
  double mean_out = 0, mean_truth = 0;
};

Scored score_image(const torch::Tensor& rec, const Truth& truth, Scorers& scorers) {  // LPIPS's forward is not const
  Scored r;
  r.image.psnr = psnr(rec, truth.image);
  r.image.ssim = ssim(rec, truth.image);
  r.mean_out = rec.mean().item<double>();
  r.mean_truth = truth.image.mean().item<double>();
  if (scorers.with_niqe) r.image.niqe = niqe_score(scorers.niqe, rec);
  // Ratios to the truth; a truth without colour (or detail) has no ratio: NaN, left out of the mean.
  r.image.colour_kept = truth.colour > 1e-6 ? colourfulness(rec) / truth.colour : std::nan("");
  r.image.detail_kept = truth.detail > 1e-6 ? luma_detail(rec) / truth.detail : std::nan("");
  r.image.stripes = stripe_energy(rec, truth.image);
  if (scorers.with_lpips) {
    torch::NoGradGuard no_grad;
    r.image.lpips = scorers.lpips->forward(rec.unsqueeze(0), truth.image.unsqueeze(0)).item<double>();  // {1,3,H,W}
  }
  return r;
}

// metrics.csv: image,method,psnr,ssim,mean_output,mean_truth[,niqe],colour_kept,detail_kept[,lpips_NET],stripes
// (stripes last: scripts that read the earlier columns by position keep working).
std::string csv_header(const Scorers& scorers) {
  return std::string("image,method,psnr,ssim,mean_output,mean_truth") + (scorers.with_niqe ? ",niqe" : "") +
         ",colour_kept,detail_kept" + (scorers.with_lpips ? ",lpips_" + scorers.lpips_net : "") + ",stripes\n";
}

void write_csv_row(std::ostream& csv, const Scored& r, const Scorers& scorers) {
  csv << r.image.image << "," << r.image.method << "," << r.image.psnr << "," << r.image.ssim << "," << r.mean_out
      << "," << r.mean_truth;
  if (scorers.with_niqe) csv << "," << r.image.niqe;
  csv << "," << r.image.colour_kept << "," << r.image.detail_kept;
  if (scorers.with_lpips) csv << "," << r.image.lpips;
  csv << "," << r.image.stripes << "\n";
}

// One method's running totals over the images, and its MethodScore (and mean row) at the end.
struct MethodTotals {
  int64_t count = 0;
  double psnr = 0, psnr_sq = 0, ssim = 0, ssim_sq = 0, out = 0, truth = 0;  // plain sums over every image
  FiniteStats niqe, colour, detail, lpips, stripes;

  void add(const Scored& r) {
    ++count;
    psnr += r.image.psnr, psnr_sq += r.image.psnr * r.image.psnr;
    ssim += r.image.ssim, ssim_sq += r.image.ssim * r.image.ssim;
    out += r.mean_out, truth += r.mean_truth;
    niqe.add(r.image.niqe), colour.add(r.image.colour_kept), detail.add(r.image.detail_kept);
    lpips.add(r.image.lpips), stripes.add(r.image.stripes);
  }

  MethodScore finish(const std::string& method, const Scorers& scorers) const {
    MethodScore s;
    s.method = method;
    s.count = count;
    s.psnr = psnr / count;
    s.ssim = ssim / count;
    s.psnr_sd = std::sqrt(std::max(0.0, psnr_sq / count - s.psnr * s.psnr));
    s.ssim_sd = std::sqrt(std::max(0.0, ssim_sq / count - s.ssim * s.ssim));
    s.brightness = truth > 0 ? out / truth : 0;
    if (scorers.with_niqe && niqe.n > 0) s.niqe = niqe.mean(), s.niqe_sd = niqe.sd();
    if (colour.n > 0) s.colour_kept = colour.mean();
    if (detail.n > 0) s.detail_kept = detail.mean();
    if (stripes.n > 0) s.stripes = stripes.mean();
    if (scorers.with_lpips) {
      s.lpips_net = scorers.lpips_net;
      if (lpips.n > 0) s.lpips = lpips.mean(), s.lpips_sd = lpips.sd();
    }
    return s;
  }

  // The method's "mean" row of metrics.csv (an empty NIQE cell where no image had one).
  void write_mean_row(std::ostream& csv, const MethodScore& s, const Scorers& scorers) const {
    csv << "mean," << s.method << "," << s.psnr << "," << s.ssim << "," << out / count << "," << truth / count;
    if (scorers.with_niqe) {
      csv << ",";
      if (niqe.n > 0) csv << s.niqe;
    }
    csv << "," << s.colour_kept << "," << s.detail_kept;
    if (scorers.with_lpips) csv << "," << s.lpips;
    csv << "," << s.stripes << "\n";
  }
};

// The truth's own NIQE row (per image and mean): its other columns are empty.
void write_truth_row(std::ostream& csv, const std::string& image, double mean_truth, double niqe,
                     const Scorers& scorers) {
  csv << image << ",ground truth,,,," << mean_truth << "," << niqe << ",," << (scorers.with_lpips ? "," : "") << ",\n";
}

std::vector<Method> chosen_methods(const EvalOptions& opt) {
  std::vector<Method> methods;
  for (const auto& name : opt.methods) {
    require(std::filesystem::is_directory(opt.out / name), opt.out / name, "no reconstructions of this method");
    methods.push_back({name, opt.out / name});
  }
  return methods.empty() ? find_methods(opt.out) : methods;
}

}  // namespace

std::vector<MethodScore> evaluate(const EvalOptions& opt, std::vector<ImageScore>* per_image) {
  const auto gt_files = list_images(opt.gt, kImageExtensions);
  require(!gt_files.empty(), opt.gt, "no ground-truth images in this folder");
  const auto methods = chosen_methods(opt);
  auto scorers = load_scorers(opt);
  std::ostringstream csv;
  csv << csv_header(scorers) << std::fixed << std::setprecision(4);
  std::vector<MethodTotals> totals(methods.size());
  FiniteStats truth_niqe;
  std::vector<std::vector<torch::Tensor>> sheet;  // rows: the truth, then each method ({3,H,W} each)
  std::vector<std::string> row_labels;
  for (const auto& gt_path : gt_files) {
    const auto name = gt_path.stem().string() + ".png";
    const bool on_sheet = static_cast<int>(sheet.size()) < opt.sheet_rows;
    std::vector<torch::Tensor> row;
    Truth truth;
    for (size_t k = 0; k < methods.size(); ++k) {
      const auto rec_path = methods[k].dir / name;
      if (!std::filesystem::exists(rec_path)) continue;
      const auto rec = read_rgb(rec_path);
      if (!truth.image.defined()) {
        truth.image = truth_for(gt_path, rec_path, rec);
        truth.colour = colourfulness(truth.image);
        truth.detail = luma_detail(truth.image);
      }
      require(rec.sizes() == truth.image.sizes(), rec_path, "size differs from the other reconstructions");
      auto scored = score_image(rec, truth, scorers);
      scored.image.image = name;
      scored.image.method = methods[k].name;
      write_csv_row(csv, scored, scorers);
      if (per_image) per_image->push_back(scored.image);
      totals[k].add(scored);
      if (on_sheet) {
        if (row.empty()) row.resize(methods.size() + 1);
        row[k + 1] = rec;
      }
    }
    if (scorers.with_niqe && truth.image.defined()) {
      const double q = niqe_score(scorers.niqe, truth.image);
      truth_niqe.add(q);
      write_truth_row(csv, name, truth.image.mean().item<double>(), q, scorers);
    }
    if (!row.empty() && on_sheet) {
      row[0] = truth.image;
      for (auto& t : row)
        if (!t.defined()) t = torch::ones_like(truth.image);
      sheet.push_back(row);
      row_labels.push_back(gt_path.stem().string());
    }
  }
  std::vector<MethodScore> scores;
  for (size_t k = 0; k < methods.size(); ++k) {
    require(totals[k].count > 0, opt.out / methods[k].name,
            "no file matches a ground-truth name in " + opt.gt.string());
    scores.push_back(totals[k].finish(methods[k].name, scorers));
    totals[k].write_mean_row(csv, scores.back(), scorers);
  }
  if (scorers.with_niqe && truth_niqe.n > 0) {
    MethodScore truth;
    truth.method = "ground truth";
    truth.count = truth_niqe.n;
    truth.psnr = truth.ssim = truth.psnr_sd = truth.ssim_sd = truth.brightness = std::nan("");
    truth.niqe = truth_niqe.mean();
    truth.niqe_sd = truth_niqe.sd();
    csv << "mean,ground truth,,,,," << truth.niqe << ",," << (scorers.with_lpips ? "," : "") << ",\n";
    scores.push_back(truth);
  }
  write_text_atomically(opt.out / "metrics.csv", csv.str());
  write_text_atomically(opt.out / "scores.json", scores_json(scores));
  std::vector<std::string> labels{"ground truth"};
  for (const auto& m : methods) labels.push_back(m.name);
  write_contact_sheet(opt.out / "sheet.png", labels, row_labels, sheet);
  return scores;
}

std::string scores_json(const std::vector<MethodScore>& scores) {
  auto number = [](double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); };
  nlohmann::json all = nlohmann::json::object();
  for (const auto& s : scores) {
    all[s.method] = {{"images", s.count},
                     {"psnr", number(s.psnr)},
                     {"psnr_sd", number(s.psnr_sd)},
                     {"ssim", number(s.ssim)},
                     {"ssim_sd", number(s.ssim_sd)},
                     {"brightness", number(s.brightness)},
                     {"niqe", number(s.niqe)},
                     {"colour_kept", number(s.colour_kept)},
                     {"detail_kept", number(s.detail_kept)},
                     {"stripes", number(s.stripes)}};
    if (!s.lpips_net.empty()) all[s.method]["lpips"] = number(s.lpips), all[s.method]["lpips_net"] = s.lpips_net;
  }
  return all.dump(2) + "\n";
}

std::string format_table(const std::vector<MethodScore>& scores) {
  bool any_niqe = false;
  std::string lpips_net;
  for (const auto& s : scores) {
    any_niqe = any_niqe || std::isfinite(s.niqe);
    if (std::isfinite(s.lpips)) lpips_net = s.lpips_net;
  }
  auto pm = [](double mean, double sd, int digits) {
    if (!std::isfinite(mean)) return std::string("-");
    std::ostringstream o;
    o << std::fixed << std::setprecision(digits) << mean << " +- " << sd;
    return o.str();
  };
  std::ostringstream os;
  os << std::left << std::setw(24) << "method" << std::right << std::setw(7) << "images" << std::setw(16) << "PSNR dB"
     << std::setw(16) << "SSIM" << std::setw(12) << "brightness" << std::setw(9) << "colour" << std::setw(9) << "detail"
     << (any_niqe ? "            NIQE" : "");
  if (!lpips_net.empty()) os << std::setw(17) << "LPIPS " + lpips_net;
  os << std::setw(9) << "stripes"
     << "\n";
  auto ratio = [](double v) {
    std::ostringstream o;
    if (std::isfinite(v))
      o << std::fixed << std::setprecision(2) << v;
    else
      o << "-";
    return o.str();
  };
  for (const auto& s : scores) {
    std::ostringstream b;
    if (std::isfinite(s.brightness))
      b << std::fixed << std::setprecision(2) << s.brightness;
    else
      b << "-";
    os << std::left << std::setw(24) << s.method << std::right << std::setw(7) << s.count << std::setw(16)
       << pm(s.psnr, s.psnr_sd, 2) << std::setw(16) << pm(s.ssim, s.ssim_sd, 3) << std::setw(12) << b.str()
       << std::setw(9) << ratio(s.colour_kept) << std::setw(9) << ratio(s.detail_kept);
    if (any_niqe) os << std::setw(16) << pm(s.niqe, s.niqe_sd, 2);
    if (!lpips_net.empty()) os << std::setw(17) << pm(s.lpips, s.lpips_sd, 3);
    os << std::setw(9) << ratio(s.stripes) << "\n";
  }
  return os.str();
}

}  // namespace flatnet
