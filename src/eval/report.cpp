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

}  // namespace

std::vector<MethodScore> evaluate(const EvalOptions& opt, std::vector<ImageScore>* per_image) {
  const auto gt_files = list_images(opt.gt, kImageExtensions);
  require(!gt_files.empty(), opt.gt, "no ground-truth images in this folder");
  std::vector<Method> methods;
  for (const auto& name : opt.methods) {
    require(std::filesystem::is_directory(opt.out / name), opt.out / name, "no reconstructions of this method");
    methods.push_back({name, opt.out / name});
  }
  if (methods.empty()) methods = find_methods(opt.out);
  NiqeModel niqe_model;
  const bool with_niqe = !opt.niqe_model.empty();
  if (with_niqe) niqe_model = load_niqe(opt.niqe_model);
  // Running sums of a NIQE column: {sum, sum of squares, count} (NaN scores, flat images, skipped).
  struct Sums {
    double sum = 0, sq = 0;
    int64_t n = 0;
  };
  auto add = [](Sums& s, double v) {
    if (std::isfinite(v)) s.sum += v, s.sq += v * v, ++s.n;
  };
  std::vector<Sums> niqe_sums(methods.size()), colour_sums(methods.size()), detail_sums(methods.size()),
      lpips_sums(methods.size());
  const bool with_lpips = !opt.lpips.empty();
  Lpips lpips{nullptr};
  if (with_lpips) lpips = load_lpips(parse_lpips_backbone(opt.lpips), opt.lpips_files);
  Sums truth_niqe;
  std::ostringstream csv;
  csv << "image,method,psnr,ssim,mean_output,mean_truth" << (with_niqe ? ",niqe" : "") << ",colour_kept,detail_kept"
      << (with_lpips ? ",lpips_" + opt.lpips : "") << "\n"
      << std::fixed << std::setprecision(4);
  std::vector<MethodScore> scores;
  std::vector<std::vector<torch::Tensor>> sheet;
  std::vector<std::string> row_labels;
  for (const auto& m : methods) scores.push_back({m.name});
  std::vector<double> sum_sq_psnr(methods.size()), sum_sq_ssim(methods.size()), sum_out(methods.size()),
      sum_gt(methods.size());
  for (const auto& gt_path : gt_files) {
    const auto name = gt_path.stem().string() + ".png";
    std::vector<torch::Tensor> row;
    torch::Tensor gt;
    double gt_colour = 0, gt_detail = 0;
    for (size_t k = 0; k < methods.size(); ++k) {
      const auto rec_path = methods[k].dir / name;
      if (!std::filesystem::exists(rec_path)) continue;
      auto rec = read_rgb(rec_path);
      if (!gt.defined()) {
        const auto truth = read_rgb(gt_path);
        // Reconstructions at another resolution are compared with the truth resized; another shape
        // (a raw capture, a crop) is a wrong folder, not a score.
        const double rec_aspect = double(rec.size(2)) / rec.size(1), gt_aspect = double(truth.size(2)) / truth.size(1);
        require(std::abs(rec_aspect / gt_aspect - 1) < 0.01, rec_path,
                "is " + std::to_string(rec.size(2)) + "x" + std::to_string(rec.size(1)) + ", its ground truth " +
                    std::to_string(truth.size(2)) + "x" + std::to_string(truth.size(1)) +
                    ": not a reconstruction of that scene (is --out a folder of reconstructions?)");
        gt = resize(truth, rec.size(1), rec.size(2));
        gt_colour = colourfulness(gt), gt_detail = luma_detail(gt);
      }
      require(rec.sizes() == gt.sizes(), rec_path, "size differs from the other reconstructions");
      const double p = psnr(rec, gt), s = ssim(rec, gt);
      const double mean_out = rec.mean().item<double>(), mean_gt = gt.mean().item<double>();
      csv << name << "," << methods[k].name << "," << p << "," << s << "," << mean_out << "," << mean_gt;
      ImageScore image{name, methods[k].name, p, s};
      if (with_niqe) {
        const double q = niqe_score(niqe_model, rec);
        add(niqe_sums[k], q);
        csv << "," << q;
        image.niqe = q;
      }
      // Ratios to the truth; a truth without colour (or detail) has no ratio: NaN, left out of the mean.
      const double colour_kept = gt_colour > 1e-6 ? colourfulness(rec) / gt_colour : std::nan("");
      const double detail_kept = gt_detail > 1e-6 ? luma_detail(rec) / gt_detail : std::nan("");
      add(colour_sums[k], colour_kept);
      add(detail_sums[k], detail_kept);
      csv << "," << colour_kept << "," << detail_kept;
      image.colour_kept = colour_kept, image.detail_kept = detail_kept;
      if (with_lpips) {
        torch::NoGradGuard no_grad;
        const double d = lpips->forward(rec.unsqueeze(0), gt.unsqueeze(0)).item<double>();  // {1,3,H,W} each
        add(lpips_sums[k], d);
        csv << "," << d;
        image.lpips = d;
      }
      csv << "\n";
      if (per_image) per_image->push_back(image);
      scores[k].count++;
      scores[k].psnr += p;
      scores[k].ssim += s;
      sum_sq_psnr[k] += p * p, sum_sq_ssim[k] += s * s, sum_out[k] += mean_out, sum_gt[k] += mean_gt;
      if (static_cast<int>(sheet.size()) < opt.sheet_rows) {
        if (row.empty()) row.resize(methods.size() + 1);
        row[k + 1] = rec;
      }
    }
    if (with_niqe && gt.defined()) {
      const double q = niqe_score(niqe_model, gt);
      add(truth_niqe, q);
      csv << name << ",ground truth,,,," << gt.mean().item<double>() << "," << q << ",," << (with_lpips ? "," : "")
          << "\n";
    }
    if (!row.empty() && static_cast<int>(sheet.size()) < opt.sheet_rows) {
      row[0] = gt;
      for (auto& t : row)
        if (!t.defined()) t = torch::ones_like(gt);
      sheet.push_back(row);
      row_labels.push_back(gt_path.stem().string());
    }
  }
  for (size_t k = 0; k < scores.size(); ++k) {
    auto& s = scores[k];
    require(s.count > 0, opt.out / s.method, "no file matches a ground-truth name in " + opt.gt.string());
    s.psnr /= s.count;
    s.ssim /= s.count;
    s.psnr_sd = std::sqrt(std::max(0.0, sum_sq_psnr[k] / s.count - s.psnr * s.psnr));
    s.ssim_sd = std::sqrt(std::max(0.0, sum_sq_ssim[k] / s.count - s.ssim * s.ssim));
    s.brightness = sum_gt[k] > 0 ? sum_out[k] / sum_gt[k] : 0;
    csv << "mean," << s.method << "," << s.psnr << "," << s.ssim << "," << sum_out[k] / s.count << ","
        << sum_gt[k] / s.count;
    if (with_niqe && niqe_sums[k].n > 0) {
      s.niqe = niqe_sums[k].sum / niqe_sums[k].n;
      s.niqe_sd = std::sqrt(std::max(0.0, niqe_sums[k].sq / niqe_sums[k].n - s.niqe * s.niqe));
      csv << "," << s.niqe;
    } else if (with_niqe) {
      csv << ",";
    }
    if (colour_sums[k].n > 0) s.colour_kept = colour_sums[k].sum / colour_sums[k].n;
    if (detail_sums[k].n > 0) s.detail_kept = detail_sums[k].sum / detail_sums[k].n;
    csv << "," << s.colour_kept << "," << s.detail_kept;
    if (with_lpips) {
      s.lpips_net = opt.lpips;
      if (lpips_sums[k].n > 0) {
        s.lpips = lpips_sums[k].sum / lpips_sums[k].n;
        s.lpips_sd = std::sqrt(std::max(0.0, lpips_sums[k].sq / lpips_sums[k].n - s.lpips * s.lpips));
      }
      csv << "," << s.lpips;
    }
    csv << "\n";
  }
  if (with_niqe && truth_niqe.n > 0) {
    MethodScore truth{"ground truth"};
    truth.count = truth_niqe.n;
    truth.psnr = truth.ssim = truth.psnr_sd = truth.ssim_sd = truth.brightness = std::nan("");
    truth.niqe = truth_niqe.sum / truth_niqe.n;
    truth.niqe_sd = std::sqrt(std::max(0.0, truth_niqe.sq / truth_niqe.n - truth.niqe * truth.niqe));
    csv << "mean,ground truth,,,,," << truth.niqe << ",," << (with_lpips ? "," : "") << "\n";
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
    all[s.method] = {{"images", s.count},           {"psnr", number(s.psnr)},
                     {"psnr_sd", number(s.psnr_sd)}, {"ssim", number(s.ssim)},
                     {"ssim_sd", number(s.ssim_sd)}, {"brightness", number(s.brightness)},
                     {"niqe", number(s.niqe)},       {"colour_kept", number(s.colour_kept)},
                     {"detail_kept", number(s.detail_kept)}};
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
     << std::setw(16) << "SSIM" << std::setw(12) << "brightness" << std::setw(9) << "colour" << std::setw(9)
     << "detail" << (any_niqe ? "            NIQE" : "");
  if (!lpips_net.empty()) os << std::setw(17) << "LPIPS " + lpips_net;
  os << "\n";
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
    os << "\n";
  }
  return os.str();
}

}  // namespace flatnet
