#include "optics/simulator.hpp"

#include <atomic>
#include <iomanip>
#include <iostream>
#include <map>
#include <sstream>
#include <random>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/yaml_text.hpp"

namespace flatnet {

torch::Tensor display_scene(const std::filesystem::path& image, int64_t size) {
  auto rgb = resize(read_rgb(image), size, size);
  return torch::round(rgb.clamp(0, 1) * 255.0f) / 255.0f;  // what an 8-bit display shows
}

torch::Tensor lit_scene(const torch::Tensor& display_srgb, const SceneLight& light, double display_gamma) {
  auto linear = display_to_light(display_srgb.to(torch::kFloat32), display_gamma) * light.exposure;  // {3,N,N}
  if (light.lamp) {
    const int64_t N = linear.size(-1);
    const auto idx = torch::arange(N, torch::kFloat32) + 0.5f;
    const auto dy = (idx - static_cast<float>(light.lamp_row)).view({N, 1}),
               dx = (idx - static_cast<float>(light.lamp_col)).view({1, N});
    // A disk with a one-pixel soft edge, slightly warm (an incandescent or LED lamp, not the display's white).
    const auto disk = (static_cast<float>(light.lamp_radius) + 0.5f - torch::sqrt(dy * dy + dx * dx)).clamp(0, 1);
    const auto colour = torch::tensor({1.0f, 0.92f, 0.8f}).view({3, 1, 1});
    linear = linear + static_cast<float>(light.lamp_gain) * colour * disk.unsqueeze(0);
  }
  return linear;
}

torch::Tensor visible_scene(const torch::Tensor& linear, double display_gamma) {
  // As an 8-bit ground-truth image (light_to_display clips to display white).
  return torch::round(light_to_display(linear, display_gamma) * 255.0f) / 255.0f;
}

void place_lamp(SceneLight& light, int64_t n, at::Generator& gen) {
  const auto u = at::rand({3}, gen);
  light.lamp = true;
  light.lamp_row = 8 + u[0].item<double>() * static_cast<double>(n - 16);
  light.lamp_col = 8 + u[1].item<double>() * static_cast<double>(n - 16);
  light.lamp_radius = 1.5 + 2.5 * u[2].item<double>();
}

SceneLight draw_scene_light(const LightAugment& a, int64_t n, at::Generator& gen) {
  SceneLight light;
  const auto u = at::rand({4}, gen);
  auto log_uniform = [](double lo, double hi, double t) {
    return std::exp(std::log(lo) + t * (std::log(hi) - std::log(lo)));
  };
  if (u[0].item<double>() < a.exposure_probability)
    light.exposure = log_uniform(a.exposure_min, a.exposure_max, u[1].item<double>());
  if (u[2].item<double>() < a.lamp_probability) {
    place_lamp(light, n, gen);
    light.lamp_gain = log_uniform(a.lamp_min, a.lamp_max, u[3].item<double>());
  }
  return light;
}

std::pair<std::vector<std::string>, std::vector<std::string>> split_train_val(const std::vector<std::string>& names,
                                                                              double val_fraction, uint64_t seed) {
  std::vector<std::string> shuffled = names;
  std::mt19937_64 rng(seed);
  std::shuffle(shuffled.begin(), shuffled.end(), rng);
  const auto n_val = static_cast<size_t>(std::llround(val_fraction * shuffled.size()));
  std::vector<std::string> val(shuffled.begin(), shuffled.begin() + n_val),
      train(shuffled.begin() + n_val, shuffled.end());
  std::sort(val.begin(), val.end());
  std::sort(train.begin(), train.end());
  return {train, val};
}

std::pair<std::vector<std::filesystem::path>, std::vector<std::filesystem::path>> split_image_files(
    const std::filesystem::path& dir, double val_fraction, uint64_t seed) {
  const auto images = list_images(dir, kImageExtensions);
  require(!images.empty(), dir, "no readable images (png, jpg, tif, bmp) in this folder");
  std::vector<std::string> names;
  std::map<std::string, std::filesystem::path> by_name;
  for (const auto& p : images) names.push_back(p.filename().string()), by_name[p.filename().string()] = p;
  auto [train, val] = split_train_val(names, val_fraction, seed);
  std::vector<std::filesystem::path> a, b;
  for (const auto& n : train) a.push_back(by_name.at(n));
  for (const auto& n : val) b.push_back(by_name.at(n));
  return {a, b};
}

namespace {

void write_lists(const std::filesystem::path& out, const std::string& split, const std::vector<std::string>& names) {
  std::string meas, gt;
  for (const auto& n : names) {
    meas += "meas/" + n + "\n";
    gt += "gt/" + n + "\n";
  }
  write_text_atomically(out / (split + "_meas.txt"), meas);
  write_text_atomically(out / (split + "_gt.txt"), gt);
}

}  // namespace

std::pair<int64_t, int64_t> write_dataset_lists(const std::filesystem::path& out, const std::vector<std::string>& names,
                                                const std::vector<std::string>& complete, double val_fraction,
                                                uint64_t seed) {
  auto [train, val] = split_train_val(names, val_fraction, seed);
  auto done = complete;
  std::sort(done.begin(), done.end());
  auto keep_done = [&](std::vector<std::string>& v) {
    v.erase(std::remove_if(v.begin(), v.end(),
                           [&](const std::string& n) { return !std::binary_search(done.begin(), done.end(), n); }),
            v.end());
  };
  keep_done(train);
  keep_done(val);
  write_lists(out, "train", train);
  write_lists(out, "val", val);
  return {static_cast<int64_t>(train.size()), static_cast<int64_t>(val.size())};
}

namespace {

// The settings a dataset's captures depend on, one "key: value" per line (OUT/simulate.yaml).
// --limit and --only are not among them: they choose which of the same captures to make.
std::vector<std::pair<std::string, std::string>> dataset_settings(const SimulateOptions& opt) {
  std::error_code ec;
  auto images = std::filesystem::weakly_canonical(opt.images, ec);
  if (ec) images = std::filesystem::absolute(opt.images);
  auto number = [](double v) {
    std::ostringstream s;
    s << std::setprecision(17) << v;
    return s.str();
  };
  return {{"images", images.string()},
          {"camera", opt.camera},
          {"seed", std::to_string(opt.seed)},
          {"noise", opt.noise ? "on" : "off"},
          {"size", std::to_string(opt.size)},
          {"val_fraction", number(opt.val_fraction)},
          {"exposure", number(opt.exposure)},
          {"lamp", opt.lamp ? "on" : "off"},
          {"lamp_gain", opt.lamp ? number(opt.lamp_gain) : "-"}};
}

// The record as YAML (values are written quoted: a folder named "a: b #c" or holding a newline reads
// back as itself); a record that is not a mapping of scalars, as from before quoting, line by line.
std::map<std::string, std::string> read_settings(const std::filesystem::path& file) {
  std::map<std::string, std::string> out;
  try {
    const auto doc = parse_yaml_document(read_file_text(file, 1 << 20), file);
    bool scalars = doc.IsMap();
    for (const auto& kv : doc.IsMap() ? doc : YAML::Node())
      if (kv.first.IsScalar() && (kv.second.IsScalar() || kv.second.IsNull()))
        out[kv.first.Scalar()] = kv.second.IsNull() ? "" : kv.second.Scalar();
      else
        scalars = false;  // an unquoted "lamp_gain: -" of an older record reads as a list
    if (scalars) return out;
  } catch (const Error&) {
  }
  out.clear();
  for (const auto& line : read_lines(file)) {
    if (line.empty() || line[0] == '#') continue;
    const auto colon = line.find(':');  // keys hold no colon; "camera:" is an empty value
    if (colon == std::string::npos) continue;
    auto value = line.substr(colon + 1);
    if (!value.empty() && value[0] == ' ') value.erase(0, 1);
    out[line.substr(0, colon)] = value;
  }
  return out;
}

// Refuses to add captures made with other settings to a dataset (unless opt.force, which deletes
// the old captures and lists), then records this run's settings.
void check_and_record_settings(const SimulateOptions& opt) {
  const auto record = opt.out / "simulate.yaml";
  const auto settings = dataset_settings(opt);
  if (std::filesystem::exists(record)) {
    const auto old = read_settings(record);
    std::string differences;
    for (const auto& [key, value] : settings) {
      const auto it = old.find(key);
      const std::string was = it == old.end() ? "(not recorded)" : it->second;
      if (was != value) differences += (differences.empty() ? "" : ", ") + key + " " + was + " -> " + value;
    }
    if (!differences.empty() && !opt.force)
      throw Error(opt.out, "holds captures simulated with other settings (" + differences +
                               "); rerun with the recorded settings to resume, choose another " +
                               option_key("simulate.out") + ", or set " + option_key("simulate.force") +
                               " "
                               "to delete its captures and rebuild");
    if (!differences.empty()) {
      std::cerr << "simulate: --force: deleting " << opt.out.string() << "'s captures and lists (" << differences
                << ")\n";
      for (const char* folder : {"meas", "gt"}) std::filesystem::remove_all(opt.out / folder);
      for (const char* list : {"train_meas.txt", "train_gt.txt", "val_meas.txt", "val_gt.txt"})
        std::filesystem::remove(opt.out / list);
    }
  } else if (std::filesystem::exists(opt.out / "meas") && !std::filesystem::is_empty(opt.out / "meas")) {
    std::cerr << "simulate: " << opt.out.string()
              << " has captures but no settings record; adding to them and recording "
              << "this run's settings in simulate.yaml\n";
  }
  std::string text = "# the settings of `flatnet simulate` that made this dataset (a rerun must match them)\n";
  for (const auto& [key, value] : settings) text += key + ": " + yaml_quoted(value) + "\n";
  std::filesystem::create_directories(opt.out);
  write_text_atomically(record, text);
}

// Each pair records the photograph it was made from (its content fingerprint) in
// OUT/.sources/NAME.txt, written after both images. A pair is reused only when that record matches
// the photograph as it is now and both images decode at the sizes this rig makes; anything else (a
// capture cut short, an empty gt file, an edited photograph, a pair from before the records) is
// simulated again.
std::filesystem::path source_record(const std::filesystem::path& out, const std::string& name) {
  return out / ".sources" / (name + ".txt");
}

bool reusable_pair(const Rig& rig, const std::filesystem::path& meas, const std::filesystem::path& gt,
                   const std::filesystem::path& record, const std::string& photo_fingerprint, int64_t size) {
  if (!std::filesystem::exists(meas) || !std::filesystem::exists(gt) || !std::filesystem::exists(record)) return false;
  try {
    if (read_file_text(record, 1024) != photo_fingerprint + "\n") return false;
    const auto raw = read_gray16(meas);  // {H,W}: the Bayer mosaic, two rows and columns per plane pixel
    const auto scene = read_rgb(gt);     // {3,N,N}
    return raw.dim() == 2 && raw.size(0) == 2 * rig.phil.size(1) && raw.size(1) == 2 * rig.phir.size(1) &&
           scene.dim() == 3 && scene.size(1) == size && scene.size(2) == size;
  } catch (const std::exception&) {
    return false;  // undecodable: made again
  }
}

}  // namespace

SimulateReport simulate_dataset(const Rig& rig, const SimulateOptions& opt) {
  require_option(opt.val_fraction >= 0 && opt.val_fraction <= 1, "simulate.val_fraction", "must be within [0, 1]");
  require_option(std::isfinite(opt.exposure) && opt.exposure > 0 && opt.exposure <= 100, "simulate.exposure",
                 "must lie in (0, 100] (scene light relative to the display's)");
  require_option(std::isfinite(opt.lamp_gain) && opt.lamp_gain > 0 && opt.lamp_gain <= 1e4, "simulate.lamp_gain",
                 "must lie in (0, 10000]");
  require_option(opt.size == rig.scene_size(), "simulate.size",
                 "the rig's matrices take " + std::to_string(rig.scene_size()) + "x" +
                     std::to_string(rig.scene_size()) + " scenes, got " + std::to_string(opt.size));
  auto images = list_images(opt.images, kImageExtensions);
  if (opt.limit > 0 && static_cast<int64_t>(images.size()) > opt.limit) images.resize(opt.limit);
  require(!images.empty(), opt.images, "no images (.png .jpg .jpeg .tif .bmp) in this folder");
  std::vector<std::string> names;
  for (const auto& p : images) names.push_back(p.stem().string() + ".png");
  for (size_t i = 1; i < names.size(); ++i)
    require(names[i] != names[i - 1], images[i], "two images share the name " + names[i]);
  const auto all_names = names;
  require_option(opt.only == "all" || opt.only == "train" || opt.only == "val", "simulate.only",
                 "must be all, train or val");
  if (opt.only != "all") {  // keep one side of the split; the lists below still use the split of all names
    const auto [train, val] = split_train_val(names, opt.val_fraction, opt.seed);
    const auto& keep = opt.only == "val" ? val : train;
    std::vector<std::filesystem::path> kept_images;
    std::vector<std::string> kept_names;
    for (size_t i = 0; i < names.size(); ++i)
      if (std::binary_search(keep.begin(), keep.end(), names[i]))
        kept_images.push_back(images[i]), kept_names.push_back(names[i]);
    images = kept_images;
    names = kept_names;
    require(!images.empty(), option_key("simulate.only") + " " + opt.only,
            "selects no images (" + option_key("simulate.val_fraction") + " " + std::to_string(opt.val_fraction) +
                " of " + std::to_string(all_names.size()) + ")");
  }

  check_and_record_settings(opt);
  std::filesystem::create_directories(opt.out / "meas");
  std::filesystem::create_directories(opt.out / "gt");
  std::filesystem::create_directories(opt.out / ".sources");
  SimulateReport report;
  report.total = static_cast<int64_t>(images.size());

  const int workers = opt.workers > 0 ? opt.workers : all_cores();
  std::atomic<int64_t> simulated{0}, skipped{0}, clipped{0};
  const int64_t full_scale = ((int64_t{1} << rig.adc_bits) - 1) << (16 - rig.adc_bits);  // a stored code
  Progress progress("simulate", report.total, opt.progress);
  const auto start = std::chrono::steady_clock::now();
  // One photograph per call; the first error stops the others from starting (parallel_for_index).
  const auto simulate_one = [&](int64_t i) {
    c10::InferenceMode guard;
    const auto meas_path = opt.out / "meas" / names[i], gt_path = opt.out / "gt" / names[i];
    const auto record = source_record(opt.out, names[i]);
    require(names[i].find_first_of("\n\r") == std::string::npos, images[i],
            "a photograph's name holds a line break (the dataset's list files are one name per line)");
    const auto fingerprint = file_fingerprint(images[i]);
    if (reusable_pair(rig, meas_path, gt_path, record, fingerprint, opt.size)) {
      ++skipped;
      progress.tick();
      return;
    }
    std::filesystem::remove(record);  // the pair is being remade: no record until both images are
    auto scene = display_scene(images[i], opt.size);
    // Per-image generator: the noise does not depend on thread scheduling.
    auto gen = at::detail::createCPUGenerator(stable_hash(names[i], opt.seed));
    torch::Tensor raw;
    if (opt.exposure == 1.0 && !opt.lamp) {
      raw = simulate_raw(rig, scene, opt.noise, gen);
    } else {  // a real scene's light: the ground truth is what the scene shows, clipped at white
      SceneLight light;
      light.exposure = opt.exposure;
      light.lamp_gain = opt.lamp_gain;
      auto lamp_gen = at::detail::createCPUGenerator(stable_hash(names[i] + "#lamp", opt.seed));
      if (opt.lamp) place_lamp(light, opt.size, lamp_gen);
      const auto linear = lit_scene(scene, light, rig.display_gamma);
      raw = simulate_raw_linear(rig, linear, opt.noise, gen);
      scene = visible_scene(linear, rig.display_gamma);
    }
    if ((raw >= full_scale).to(torch::kFloat32).mean().item<double>() > kClippedShare) ++clipped;
    write_rgb8(gt_path, scene);
    write_gray16(meas_path, raw);
    write_text_atomically(record, fingerprint + "\n");
    ++simulated;
    progress.tick();
  };
  try {
    parallel_for_index(static_cast<int64_t>(images.size()), workers, simulate_one);
  } catch (...) {
    progress.finish();
    throw;
  }
  progress.finish();
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  report.simulated = simulated;
  report.skipped = skipped;
  report.clipped = clipped;

  std::tie(report.train, report.val) = write_dataset_lists(opt.out, all_names, names, opt.val_fraction, opt.seed);
  return report;
}

}  // namespace flatnet
