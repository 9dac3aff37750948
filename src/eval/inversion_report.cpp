#include "eval/inversion_report.hpp"

#include <iomanip>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/metrics.hpp"
#include "nn/model_file.hpp"
#include "optics/camera.hpp"

namespace flatnet {

std::pair<torch::Tensor, ProductStats> inversion_product(const torch::Tensor& W, const torch::Tensor& Phi) {
  TORCH_CHECK(W.dim() == 2 && W.sizes() == Phi.sizes(), "inversion_product: equal {rows,N} matrices expected, got ",
              W.sizes(), " and ", Phi.sizes());
  const auto product = torch::matmul(W.to(torch::kFloat64).t(), Phi.to(torch::kFloat64));  // {N,N}
  const auto energy = product.pow(2);
  const double total = std::max(energy.sum().item<double>(), 1e-300);
  const int64_t n = product.size(0);
  std::vector<double> per_diagonal(2 * n - 1);  // index d + n - 1: entries with j - i = d
  for (int64_t d = -(n - 1); d <= n - 1; ++d) per_diagonal[d + n - 1] = energy.diagonal(d).sum().item<double>();
  ProductStats s;
  s.diagonal = per_diagonal[n - 1] / total;
  double best_centre = -1;
  for (int64_t d = -(n - 1); d <= n - 1; ++d) {
    double band = 0;
    for (int64_t e = std::max(-(n - 1), d - 2); e <= std::min(n - 1, d + 2); ++e) band += per_diagonal[e + n - 1];
    band /= total;
    const double centre = per_diagonal[d + n - 1];  // among equal bands, the one centred on the most energy
    if (band > s.band + 1e-12 || (band > s.band - 1e-12 && centre > best_centre))
      s.band = std::max(s.band, band), s.offset = -d, best_centre = centre;  // i - j = offset
  }
  // Row i's band: columns j with |i - j - offset| <= 2.
  const auto i = torch::arange(n, torch::kLong).unsqueeze(1), j = torch::arange(n, torch::kLong).unsqueeze(0);
  const auto in_band = (i - j - s.offset).abs() <= 2;
  const auto row_band = (energy * in_band).sum(1), row_total = energy.sum(1).clamp_min(1e-300);
  const auto stray = (row_band / row_total < 0.25).nonzero().flatten();
  for (int64_t k = 0; k < stray.numel(); ++k) s.stray_rows.push_back(stray[k].item<int64_t>());
  return {product, s};
}

std::string index_ranges(const std::vector<int64_t>& sorted) {
  if (sorted.empty()) return "none";
  std::ostringstream o;
  for (size_t a = 0; a < sorted.size();) {
    size_t b = a;
    while (b + 1 < sorted.size() && sorted[b + 1] == sorted[b] + 1) ++b;
    o << (a ? ", " : "") << sorted[a];
    if (b > a) o << "-" << sorted[b];
    a = b + 1;
  }
  return o.str();
}

namespace {

// The inversion's W1, W2 of one channel: {rows,N}, {cols,N}.
std::pair<torch::Tensor, torch::Tensor> inversion_of(Generator& g, int channel, const std::filesystem::path& file) {
  torch::Tensor L, R;
  for (const auto& p : g->named_parameters()) {
    if (p.key() == "inversion.PhiL") L = p.value().detach();
    if (p.key() == "inversion.PhiR") R = p.value().detach();
  }
  require(L.defined() && R.defined(), file, "has no trainable inversion (a Tikhonov first stage): nothing to show");
  const int k = L.size(2) == 1 ? 0 : channel;  // shared: one pair for every channel
  return {L.select(2, k), R.select(2, k)};
}

torch::Tensor shown(const torch::Tensor& product) {  // |product| / max, as an RGB image {3,N,N}
  const auto a = product.abs().to(torch::kFloat32);
  return (a / a.max().clamp_min(1e-30)).unsqueeze(0).repeat({3, 1, 1});
}

// "10 of 256: 28, 164-173".
std::string stray_text(const std::vector<int64_t>& rows, int64_t n) {
  return std::to_string(rows.size()) + " of " + std::to_string(n) + (rows.empty() ? "" : ": " + index_ranges(rows));
}

std::string share(double v) {
  std::ostringstream o;
  o << std::fixed << std::setprecision(3) << v;
  return o.str();
}

}  // namespace

std::string write_inversion_report(const InversionReportOptions& opt) {
  require(!opt.models.empty(), "report inversion", "no models given");
  std::ostringstream md;
  md << "# What the inversion learned (the thesis's Figure 3.3)\n\n"
     << "Products of the first stage's W1, W2 with the camera's calibration, `W1^T PhiL` and `W2^T PhiR` "
        "({N,N}): an identity would invert the camera exactly. Energy share: squared entries on the diagonal "
        "over all squared entries; band: within 2 of the diagonal i - j = offset, at the offset where it is largest "
        "(a shifted diagonal reproduces the scene shifted, still an inverse). Stray rows: output rows whose band holds "
        "under "
        "a quarter of their energy after training; they mix far-away scene rows, and the enhancer draws a stripe "
        "there. `inversion.png`: one row per model, |product| scaled "
        "to its largest entry, before training (the initialisation the model's config describes) and after.\n\n"
     << "| model | init | product | diagonal before | diagonal after | band before | band after (offset) | stray rows "
        "|\n"
     << "|---|---|---|---|---|---|---|---|\n";
  std::vector<std::vector<torch::Tensor>> rows;
  std::vector<std::string> names;
  for (const auto& [name, file] : opt.models) {
    auto model = load_model_file(file);
    auto camera = model.camera;
    camera.calibration = opt.calibration;  // for the initialisation (transpose) and the products
    const auto calib = load_calibration(opt.calibration, camera);  // checks its sizes against the model's camera
    const int channel = channel_index(model.spec.inversion_channel);
    Generator initial(generator_options(model.spec, camera, /*initialise=*/true));
    const auto [W1_before, W2_before] = inversion_of(initial, channel, file);
    const auto [W1_after, W2_after] = inversion_of(model.generator, channel, file);
    const auto PhiL = calib.P[channel], PhiR = calib.Q[channel];  // {rows,N}, {cols,N}
    const auto [left_before, lb] = inversion_product(W1_before, PhiL);
    const auto [left_after, la] = inversion_product(W1_after, PhiL);
    const auto [right_before, rb] = inversion_product(W2_before, PhiR);
    const auto [right_after, ra] = inversion_product(W2_after, PhiR);
    const auto& init = model.spec.inversion_init;
    md << "| " << name << " | " << init << " | W1^T PhiL | " << share(lb.diagonal) << " | " << share(la.diagonal)
       << " | " << share(lb.band) << " | " << share(la.band) << " (" << la.offset << ") | "
       << stray_text(la.stray_rows, W1_after.size(1)) << " |\n"
       << "| " << name << " | " << init << " | W2^T PhiR | " << share(rb.diagonal) << " | " << share(ra.diagonal)
       << " | " << share(rb.band) << " | " << share(ra.band) << " (" << ra.offset << ") | "
       << stray_text(ra.stray_rows, W2_after.size(1)) << " |\n";
    rows.push_back({shown(left_before), shown(left_after), shown(right_before), shown(right_after)});
    names.push_back(name);
  }
  md << "\n![products](inversion.png)\n";
  std::filesystem::create_directories(opt.out);
  // The contact sheet's first column is labelled as the others; it holds the first product.
  write_contact_sheet(opt.out / "inversion.png",
                      {"W1^T PhiL before", "W1^T PhiL after", "W2^T PhiR before", "W2^T PhiR after"}, names, rows);
  write_text_atomically(opt.out / "inversion.md", md.str());
  return md.str();
}

}  // namespace flatnet
