#include "eval/thesis_report.hpp"

#include <fstream>
#include <iostream>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/html_report.hpp"
#include "eval/metrics.hpp"
#include "eval/report.hpp"
#include "eval/tables.hpp"
#include "io/image.hpp"
#include "optics/camera.hpp"
#include "recon/batch.hpp"
#include "recon/methods.hpp"
#include "nn/model_file.hpp"

namespace flatnet {

namespace {

namespace fs = std::filesystem;

std::vector<fs::path> set_captures(const ReportSet& set) {
  const auto list = set.dir / "val_meas.txt";
  return collect_captures(fs::exists(list) ? list : set.dir / "meas");
}

fs::path output_of(const fs::path& dir, const fs::path& capture) {
  return dir / fs::path(capture.filename()).replace_extension(".png");
}

// Milliseconds per image in the method itself, as measured when its reconstructions were made
// (kept in timing.txt beside them, so that a resumed report still reports it): {ms, images timed}.
std::pair<double, int64_t> read_timing(const fs::path& dir) {
  std::ifstream in(dir / "timing.txt");
  double ms = std::nan("");
  int64_t n = 0;
  if (in) in >> ms >> n;
  return {in ? ms : std::nan(""), n};
}

void record_timing(const fs::path& dir, double ms, int64_t count) {
  const auto [old_ms, old_n] = read_timing(dir);
  double total_ms = ms * count;
  int64_t total_n = count;
  if (std::isfinite(old_ms) && old_n > 0) total_ms += old_ms * old_n, total_n += old_n;
  write_text_atomically(dir / "timing.txt", std::to_string(total_ms / total_n) + " " + std::to_string(total_n) +
                                                "\n# ms per image in the method (no file I/O), images timed\n");
}

// What a method's cached reconstructions depend on: the model file's content (not its name), or
// the classical method with its calibration's content and regularisers; and the set's folder.
std::string method_key(const ReportOptions& o, const ReportMethod& m, const ReportSet& set) {
  std::ostringstream key;
  if (m.kind == "model")
    key << "model " << file_fingerprint(m.model);
  else
    key << m.kind << " calibration " << file_fingerprint(o.camera.calibration) << " lambda " << o.camera.tikhonov_lambda
        << " tv " << o.camera.tv_lambda;
  key << "\nset " << fs::weakly_canonical(set.dir).string() << "\n";
  return key.str();
}

// Keeps the cached reconstructions in `dir` only when they were made by the same method settings
// (method.txt); otherwise they go, and the method runs again.
// A folder is emptied only when its method.txt says flatnet made it, and never through a link.
void reuse_only_same_method(const fs::path& dir, const std::string& key, const std::string& name) {
  for (const auto& p : {dir.parent_path(), dir})
    require(!fs::is_symlink(p), p, "is a symbolic link; flatnet report writes only into folders it made");
  const auto record = dir / "method.txt";
  const bool ours = fs::is_regular_file(fs::symlink_status(record));
  const bool same = ours && read_file_text(record, 1 << 16) == key;
  if (!same && fs::exists(dir) && !fs::is_empty(dir)) {
    require(ours, dir,
            "holds files that flatnet report did not write (no method.txt); move them or choose another --out");
    std::cerr << "  " << printable(name)
              << ": the reconstructions on disk were made by another model or settings; remade\n";
    fs::remove_all(dir);
  }
  fs::create_directories(dir);
  if (!same) write_text_atomically(record, key);
}

// Makes the method's reconstructions of `captures` that are not on disk yet.
void reconstruct_missing(const ReportOptions& o, const ReportMethod& m, const std::vector<fs::path>& captures,
                         const fs::path& dir, const std::shared_ptr<const Calibration>& calib) {
  std::vector<fs::path> missing;
  for (const auto& c : captures)
    if (!fs::exists(output_of(dir, c))) missing.push_back(c);
  if (missing.empty()) return;
  std::cerr << "  " << m.name << ": " << missing.size() << " of " << captures.size() << " to make\n";
  BatchOptions bo;
  bo.out = dir;
  bo.progress = o.progress;
  bo.label = m.name;
  if (m.kind == "model") {
    auto model = load_model_file(m.model);
    std::string no_fit;
    const auto fit = model_camera_fit(model, no_fit);
    bo.fit = fit.get();
    auto engine = make_flatnet(model.generator, model.camera, o.levers, m.name);
    const auto rep = reconstruct_files(*engine, model.camera, missing, bo);
    record_timing(dir, rep.ms_per_capture, rep.count);
    if (fit && rep.misfits > 0)
      std::cerr << "  " << printable(m.name) << ": warning: " << camera_fit_warning(rep, *fit) << "\n";
  } else {
    bo.batch = 8;
    ReconstructorSpec spec;
    spec.method = m.kind;
    spec.camera = o.camera;
    spec.loaded_calibration = calib;
    const auto built = require_method(m.kind, MethodInput::calibration, "report.methods").build(spec);
    const auto rep = reconstruct_files(*built.engine, built.camera, missing, bo);
    record_timing(dir, rep.ms_per_capture, rep.count);
  }
}

// Rows of scenes, a column per method, each with a magnified detail (thesis Figure 5.1).
void write_figure(const fs::path& path, const ReportSet& set, const std::vector<ReportMethod>& methods,
                  const std::vector<fs::path>& captures, const fs::path& set_out, int rows) {
  std::vector<std::vector<torch::Tensor>> images;
  std::vector<std::string> row_labels, labels{"ground truth"};
  for (const auto& m : methods) labels.push_back(m.name);
  for (const auto& c : captures) {
    if (static_cast<int>(images.size()) >= rows) break;
    const auto gt_path = set.dir / "gt" / fs::path(c.filename()).replace_extension(".png");
    bool complete = fs::exists(gt_path);
    for (const auto& m : methods) complete = complete && fs::exists(output_of(set_out / m.name, c));
    if (!complete) continue;  // TV covers only the first captures; figures show scenes every method has
    const auto gt = read_rgb(gt_path);
    const int64_t n = gt.size(1), detail = n / 6;
    const int64_t r0 = n / 2 - detail / 2, c0 = n / 2 - detail;  // a detail left of the centre
    std::vector<torch::Tensor> row{with_inset(gt, r0, c0, detail)};
    for (const auto& m : methods)
      row.push_back(with_inset(resize(read_rgb(output_of(set_out / m.name, c)), n, n), r0, c0, detail));
    images.push_back(row);
    row_labels.push_back(c.stem().string());
  }
  if (!images.empty()) write_contact_sheet(path, labels, row_labels, images);
}

}  // namespace

ReportMethod parse_report_method(const std::string& spec) {
  const auto* method = find_method(spec);
  if (method != nullptr && method->input == MethodInput::calibration) return {spec, spec, {}};
  const auto eq = spec.find('=');
  require_option(eq != std::string::npos && eq > 0 && eq + 1 < spec.size(), "report.methods",
                 "'" + spec + "': expected " + method_names(MethodInput::calibration, ", ") + " or NAME=MODEL.flatnet");
  ReportMethod m{spec.substr(0, eq), "model", spec.substr(eq + 1)};
  require_plain_name(m.name, option_key("report.methods"));
  require(fs::exists(m.model), m.model, "no such model file");
  return m;
}

ReportSet parse_report_set(const std::string& spec) {
  const auto eq = spec.find('=');
  const auto folder = fs::path(spec).lexically_normal();  // "sets/dim/" names the set "dim"
  ReportSet s = eq == std::string::npos
                    ? ReportSet{(folder.has_filename() ? folder : folder.parent_path()).filename().string(), spec}
                    : ReportSet{spec.substr(0, eq), spec.substr(eq + 1)};
  require_plain_name(s.name, option_key("report.sets"));
  require(fs::is_directory(s.dir / "gt"), s.dir,
          "not an evaluation set (no gt/ folder; make one with `flatnet simulate --only val`)");
  return s;
}

std::string make_report(const ReportOptions& o) {
  require(!o.methods.empty() && !o.sets.empty(), "report", "at least one method and one set are needed");
  for (const auto& m : o.methods)
    require_plain_name(m.name, option_key("report.methods"));  // each names a folder in --out
  for (const auto& set : o.sets) require_plain_name(set.name, option_key("report.sets"));
  for (size_t i = 0; i < o.methods.size(); ++i)
    for (size_t j = 0; j < i; ++j)
      require_option(o.methods[i].name != o.methods[j].name, "report.methods",
                     "two methods are named '" + o.methods[i].name + "'");
  for (size_t i = 0; i < o.sets.size(); ++i)
    for (size_t j = 0; j < i; ++j)
      require_option(o.sets[i].name != o.sets[j].name, "report.sets",
                     "two sets are named '" + printable(o.sets[i].name) + "'");
  fs::create_directories(o.out);
  // The calibration the classical columns solve with, read once for all of them and before any
  // column runs, so that a bad file stops the report first.
  std::shared_ptr<const Calibration> calib;
  for (const auto& m : o.methods)
    if (m.kind != "model" && !calib) {
      require(!o.camera.calibration.empty(), o.camera.name,
              "this camera names no calibration (needed for " + m.name + ")");
      calib = std::make_shared<const Calibration>(load_calibration(o.camera.calibration, o.camera));
    }

  std::ostringstream md;
  md << "# Reconstruction report\n\nMade by `" << o.command
     << "` (`flatnet report`): every method on every set, scored "
     << "against the ground truth. PSNR in dB and SSIM (11x11 Gaussian window) on the 256x256 sRGB images; NIQE "
     << "(Mittal et al. 2013; lower is more natural) with the model "
     << (o.niqe_model.empty() ? "(none)" : o.niqe_model.string())
     << ". Values are mean ± standard deviation over the images. Ma et al.'s score needs regression forests that are "
     << "not available here, so there is no perceptual index (PI); NIQE is reported alone. Time: milliseconds per "
        "image in the method itself, in steady state (no file I/O; the first batch, which also sets the engine up, "
        "left out), as `flatnet infer` and `flatnet recon` report it, on "
     << o.machine << ".\n\n";
  std::vector<HtmlSet> pages;
  for (size_t si = 0; si < o.sets.size(); ++si) {
    const auto& set = o.sets[si];
    std::cerr << "[" << si + 1 << "/" << o.sets.size() << "] " << set.name << " (" << set.dir.string() << ")\n";
    const auto captures = set_captures(set);
    const auto set_out = o.out / set.name;
    std::vector<std::string> names;
    for (const auto& m : o.methods) {
      auto subset = captures;
      if (m.kind != "model" && find_method(m.kind)->slow && o.tv_count > 0 &&
          static_cast<int64_t>(subset.size()) > o.tv_count)
        subset.resize(o.tv_count);
      reuse_only_same_method(set_out / m.name, method_key(o, m, set), m.name);
      reconstruct_missing(o, m, subset, set_out / m.name, calib);
      names.push_back(m.name);
    }
    EvalOptions eo;
    eo.gt = set.dir / "gt";
    eo.out = set_out;
    eo.niqe_model = o.niqe_model;
    eo.methods = names;
    eo.lpips = o.lpips;
    eo.lpips_files = o.lpips_files;
    HtmlSet page{set.name, std::to_string(captures.size()) + " captures from " + set.dir.string() + "."};
    const auto scores = evaluate(eo, &page.images);
    const bool with_lpips = !o.lpips.empty();
    MarkdownTable table{{"method", "images", "PSNR dB", "SSIM", "NIQE"}, {}};
    if (with_lpips) table.header.push_back("LPIPS (" + o.lpips + ")");
    table.header.push_back("ms per image");
    for (const auto& s : scores) {
      const auto [ms, timed] =
          s.method == "ground truth" ? std::pair<double, int64_t>{std::nan(""), 0} : read_timing(set_out / s.method);
      std::vector<std::string> row{s.method, std::to_string(s.count), plus_minus(s.psnr, s.psnr_sd, 2),
                                   plus_minus(s.ssim, s.ssim_sd, 3), plus_minus(s.niqe, s.niqe_sd, 2)};
      if (with_lpips) row.push_back(plus_minus(s.lpips, s.lpips_sd, 3));
      row.push_back(fixed(ms, 1));
      table.add(row);
      page.ms_per_image.push_back(ms);
    }
    page.methods = names;
    page.scores = scores;
    page.gt_dir = eo.gt;
    page.rec_dir = set_out;
    page.gallery = std::max(8, o.figure_rows);
    pages.push_back(std::move(page));
    const bool lamp = set.name.find("lamp") != std::string::npos;
    md << "## " << set.name << (lamp ? ": dynamic range (thesis Figure 5.3)" : "") << "\n\n"
       << captures.size() << " captures from `" << set.dir.string() << "`"
       << (o.tv_count > 0 ? "; TV on the first " + std::to_string(std::min<int64_t>(o.tv_count, captures.size()))
                          : std::string())
       << ".\n\n"
       << table.markdown() << "\n";
    const auto figure = set.name + "_figure.png";
    write_figure(o.out / figure, set, o.methods, captures, set_out, o.figure_rows);
    md << "![" << set.name << "](" << figure << ")\n\n";
  }
  write_text_atomically(o.out / "report.md", md.str());
  write_text_atomically(o.out / "report.html", html_report("Reconstruction report",
                                                           "Made by " + o.command + " on " + o.machine +
                                                               ". PSNR in dB and SSIM on the 256x256 sRGB images; "
                                                               "NIQE lower is more natural; LPIPS lower is closer.",
                                                           pages));
  return md.str();
}

}  // namespace flatnet
