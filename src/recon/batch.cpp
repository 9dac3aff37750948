#include "recon/batch.hpp"

#include <fnmatch.h>

#include <cmath>
#include <iomanip>
#include <map>
#include <sstream>
#include <set>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"

namespace flatnet {

std::vector<std::filesystem::path> collect_captures(const std::filesystem::path& input) {
  const auto pattern = input.filename().string();
  if (pattern.find_first_of("*?[") != std::string::npos) {  // DIR/fc_*.png: matching files, sorted
    const auto dir = input.parent_path().empty() ? std::filesystem::path(".") : input.parent_path();
    require(std::filesystem::is_directory(dir), dir, "no such folder");
    std::vector<std::filesystem::path> files;
    for (const auto& e : std::filesystem::directory_iterator(dir))
      if (e.is_regular_file() && ::fnmatch(pattern.c_str(), e.path().filename().c_str(), 0) == 0)
        files.push_back(e.path());
    std::sort(files.begin(), files.end());
    require(!files.empty(), input, "no file matches this pattern");
    return files;
  }
  require(std::filesystem::exists(input), input, "no such file or folder");
  if (std::filesystem::is_directory(input)) {
    auto files = list_images(input, {".png"});
    require(!files.empty(), input, "no .png captures in this folder");
    return files;
  }
  if (input.extension() == ".txt") {  // a list (e.g. a dataset's val_meas.txt), relative to its folder
    std::vector<std::filesystem::path> files;
    for (const auto& line : read_lines(input)) {
      const auto p = input.parent_path() / line;
      require(std::filesystem::exists(p), input, "lists '" + line + "', which does not exist");
      files.push_back(p);
    }
    require(!files.empty(), input, "an empty list");
    return files;
  }
  return {input};
}

void check_output_names(const std::vector<std::filesystem::path>& captures, const std::filesystem::path& out) {
  auto canonical = [](const std::filesystem::path& p) {
    std::error_code ec;
    auto c = std::filesystem::weakly_canonical(p, ec);
    return ec ? std::filesystem::absolute(p).lexically_normal() : c;
  };
  std::set<std::filesystem::path> inputs;
  for (const auto& c : captures) inputs.insert(canonical(c));
  std::map<std::filesystem::path, std::filesystem::path> writer_of;  // output -> the capture that makes it
  for (const auto& c : captures) {
    const auto target = canonical(out / std::filesystem::path(c.filename()).replace_extension(".png"));
    const auto [it, fresh] = writer_of.emplace(target, c);
    if (!fresh)
      throw Error(c, "has the same name as " + it->second.string() + ": both would be written to " + target.string() +
                         " (reconstruct them into separate " + option_key("recon.out") + " folders)");
    if (inputs.count(target))
      throw Error(option_key("recon.out"), "writing " + target.string() +
                                               " would overwrite a capture being read; choose another " +
                                               option_key("recon.out") + " folder");
  }
}

namespace {

// A CSV field: quoted when it holds a comma, a quote or a line break (file names may).
std::string csv_field(const std::string& text) {
  if (text.find_first_of(",\"\r\n") == std::string::npos) return text;
  std::string quoted = "\"";
  for (const char c : text) quoted += c == '"' ? std::string("\"\"") : std::string(1, c);
  return quoted + "\"";
}

struct FitRow {
  std::string name;
  CameraFitResult result;  // the capture alone
  bool matches = true;     // alone, and its batch as a whole (settle_fits)
};

// The batch judged as a whole (judge_batch): a foreign batch flags every capture of it.
BatchFit settle_fits(std::vector<FitRow>& rows, const CameraFit& fit) {
  std::vector<CameraFitResult> results;
  for (const auto& r : rows) results.push_back(r.result);
  const auto batch = judge_batch(fit, results);
  for (auto& r : rows) r.matches = r.result.matches && !batch.foreign;
  return batch;
}

void summarise_fits(BatchReport& report, const std::vector<FitRow>& rows, const BatchFit& batch, const CameraFit& fit) {
  report.batch = batch;
  for (const auto& row : rows) {
    if (!row.result.judged) ++report.unjudged;
    if (row.matches) continue;
    ++report.misfits;
    // A capture flagged only with its batch, too saturated to judge, ranks last: its fit means nothing.
    const double excess = row.result.judged ? fit.excess(row.result) : 0;
    if (excess > report.worst_excess || report.worst.empty()) {
      report.worst = row.name;
      report.worst_fit = row.result.fit;
      report.worst_excess = excess;
      report.worst_verdict = fit.verdict(row.result);
    }
  }
}

void write_fit_csv(const std::filesystem::path& path, const std::vector<FitRow>& rows) {
  std::ostringstream csv;
  csv << "name,fit,leak,alone,matches\n";
  // A saturated capture's fit means nothing: written as nan, and not flagged alone. The leak is nan
  // where it is not measured (a window too small beside the scene). alone: the capture's own tests;
  // matches: those and its batch's (judge_batch).
  for (const auto& r : rows)
    csv << csv_field(r.name) << "," << std::setprecision(6) << (r.result.judged ? r.result.fit : std::nan("")) << ","
        << (r.result.judged ? r.result.leak : std::nan("")) << "," << (r.result.matches ? 1 : 0) << ","
        << (r.matches ? 1 : 0) << "\n";
  write_text_atomically(path, csv.str());
}

// --require-fit: every capture is measured before anything is reconstructed; the fits are kept for
// camera_fit.csv, so the batch loop does not measure them again.
std::vector<FitRow> require_all_fit(const CameraFit& fit, const std::vector<std::filesystem::path>& captures,
                                    const RawGeometry& g) {
  std::vector<FitRow> rows;
  for (const auto& c : captures) rows.push_back({c.filename().string(), fit.measure(load_raw_unit(c, g))});
  BatchReport probe;
  probe.count = static_cast<int64_t>(captures.size());
  summarise_fits(probe, rows, settle_fits(rows, fit), fit);
  if (probe.misfits > 0) throw Error(option_key("recon.require_fit"), camera_fit_warning(probe, fit));
  // --require-fit asks for captures shown to fit: one that could not be judged (over 1 % of its pixels
  // clipped) is not shown to, and is refused by name like a misfit.
  for (const auto& row : rows)
    require(row.result.judged, option_key("recon.require_fit"),
            printable(row.name) +
                " cannot be judged: " + std::to_string(static_cast<int>(std::lround(100 * row.result.saturated))) +
                " % of its window is at full scale (over 1 %); shorten the exposure, or leave out --require-fit");
  return rows;
}

}  // namespace

std::string camera_fit_note(const BatchReport& report) {
  if (report.unjudged == 0) return "";
  return std::to_string(report.unjudged) + " of " + std::to_string(report.count) +
         " captures have over 1 % of their pixels at full scale: their camera fit is not judged (nan in "
         "camera_fit.csv)";
}

std::string camera_fit_warning(const BatchReport& report, const CameraFit& fit) {
  if (report.misfits == 0) return "";
  std::ostringstream line;
  line << std::setprecision(3) << report.misfits << " of " << report.count << " captures do not fit camera '"
       << printable(fit.camera_name()) << "' (";
  if (report.batch.foreign)
    line << "as a batch of one camera's captures: its median capture is " << report.batch.median_excess
         << "x the camera fit's thresholds, over " << report.batch.judged << " judged; ";
  line << "worst: " << printable(report.worst) << ", " << report.worst_verdict << "): " << misfit_advice();
  return line.str();
}

BatchReport reconstruct_files(Reconstructor& engine, const CameraConfig& camera,
                              const std::vector<std::filesystem::path>& captures, const BatchOptions& opt) {
  require_option(!captures.empty(), "recon.input", "no captures to reconstruct");
  require_option(opt.batch >= 1, "recon.batch", "must be at least 1");
  check_output_names(captures, opt.out);
  std::vector<FitRow> fits;  // in capture order
  if (opt.fit && opt.require_fit) fits = require_all_fit(*opt.fit, captures, camera.raw);
  const bool measured = !fits.empty();
  std::filesystem::create_directories(opt.out);
  c10::InferenceMode no_grad;
  BatchReport report;
  Progress progress(opt.label, static_cast<int64_t>(captures.size()), opt.progress);
  const auto start = std::chrono::steady_clock::now();
  double engine_s = 0, first_batch_s = 0;
  int64_t first_batch_count = 0;
  for (size_t first = 0; first < captures.size(); first += opt.batch) {
    const size_t last = std::min(captures.size(), first + static_cast<size_t>(opt.batch));
    std::vector<torch::Tensor> planes;
    for (size_t i = first; i < last; ++i) {
      const auto raw = load_raw_unit(captures[i], camera.raw);
      planes.push_back(preprocess_raw(raw, camera.raw));
      if (opt.fit && !measured) fits.push_back({captures[i].filename().string(), opt.fit->measure(raw)});
    }
    const auto t0 = std::chrono::steady_clock::now();
    const auto images = engine.reconstruct(torch::stack(planes));  // {B,4,rows,cols} -> {B,3,N,N}
    const double batch_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    engine_s += batch_s;
    if (first == 0) first_batch_s = batch_s, first_batch_count = static_cast<int64_t>(last - first);
    for (size_t i = first; i < last; ++i) {
      auto name = captures[i].filename();
      write_rgb8(opt.out / name.replace_extension(".png"), images[static_cast<int64_t>(i - first)]);
    }
    report.count += static_cast<int64_t>(last - first);
    progress.tick(static_cast<int64_t>(last - first));
  }
  progress.finish();
  if (opt.fit) {
    summarise_fits(report, fits, settle_fits(fits, *opt.fit), *opt.fit);
    write_fit_csv(opt.out / "camera_fit.csv", fits);
  }
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  report.first_batch_ms = 1000.0 * first_batch_s / std::max<int64_t>(1, first_batch_count);
  report.steady_state = report.count > first_batch_count;
  report.ms_per_capture =
      report.steady_state ? 1000.0 * (engine_s - first_batch_s) / static_cast<double>(report.count - first_batch_count)
                          : report.first_batch_ms;
  report.captures_per_s = report.count / std::max(1e-9, report.seconds);
  return report;
}

}  // namespace flatnet
