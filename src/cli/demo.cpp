#include <iostream>

#include "cli/commands.hpp"
#include "core/precision.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/report.hpp"
#include "optics/simulator.hpp"
#include "recon/batch.hpp"
#include "nn/model_file.hpp"

namespace flatnet::cli {

namespace {

// Photographs that Debian's python3-skimage ships (installed by scripts/setup.sh).
const char* kDemoImageDir = "/usr/lib/python3/dist-packages/skimage/data";
const std::vector<std::string> kDemoImages = {"astronaut.png", "chelsea.png",         "coffee.png",
                                              "rocket.jpg",    "motorcycle_left.png", "hubble_deep_field.jpg"};

std::filesystem::path gather_demo_images(const std::filesystem::path& src, const std::filesystem::path& dst) {
  std::filesystem::create_directories(dst);
  int found = 0;
  for (const auto& name : kDemoImages) {
    if (!std::filesystem::exists(src / name)) continue;
    std::filesystem::copy_file(src / name, dst / name, std::filesystem::copy_options::skip_existing);
    ++found;
  }
  require(found > 0, src,
          "no demo photographs here; run scripts/setup.sh (installs python3-skimage) or pass --images DIR");
  return dst;
}

// The trained models shipped in models/ (flatnet-sim-*.flatnet), by method name.
std::vector<std::pair<std::string, std::filesystem::path>> shipped_models() {
  std::vector<std::pair<std::string, std::filesystem::path>> out;
  const auto dir = data_dir() / "models";
  for (const std::string name : {"transpose", "calibfree"}) {
    const auto p = dir / ("flatnet-sim-" + name + ".flatnet");
    if (std::filesystem::exists(p)) out.emplace_back("flatnet-" + name, p);
  }
  return out;
}

struct DemoSettings {
  std::filesystem::path out = "demo_out";
  std::filesystem::path images;  // empty: python3-skimage's sample photographs
  std::filesystem::path camera;  // empty: the reference camera (camera_from reads the flag)
};

const FlagTable<DemoSettings>& demo_flags() {
  static const FlagTable<DemoSettings> rows = {
      {"out", &DemoSettings::out, "output folder"},
      {"images", &DemoSettings::images, "photographs to use (default: python3-skimage's sample photographs)"},
      {"camera", &DemoSettings::camera, "camera .yaml (default: the reference camera)"},
  };
  return rows;
}

}  // namespace

CommandFlags demo_command_flags() { return command_flags("demo", demo_flags()); }

int demo(int argc, char** argv) {
  cxxopts::Options o("flatnet demo", "Simulate captures of a few photographs, reconstruct them, and evaluate.");
  add_flags(o, demo_flags());
  add_force_folder(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  DemoSettings set;
  read_flags(r, demo_flags(), set);
  const auto out = set.out;
  const auto claim = claim_out(r, out, "demo");
  const auto camera = camera_from(r);
  const auto images = r.count("images") ? set.images : gather_demo_images(kDemoImageDir, out / "photos");

  std::cout << "[1/3] simulating captures with camera '" << camera.name << "'\n";
  SimulateOptions sim;
  sim.images = images;
  sim.out = out / "dataset";
  sim.val_fraction = 0;
  sim.size = camera.scene_size;
  sim.camera = std::filesystem::weakly_canonical(camera.rig).string();
  const auto srep = simulate_dataset(load_camera_rig(camera), sim);

  std::cout << "[2/3] reconstructing\n";
  const auto calib = load_calibration(camera.calibration, camera);
  const auto captures = collect_captures(sim.out / "meas");
  for (const auto method : {ClassicalMethod::tikhonov, ClassicalMethod::tv}) {
    BatchOptions bo;
    bo.out = out / "recon" / classical_method_name(method);
    bo.batch = 8;
    bo.label = classical_method_name(method);
    auto engine = make_classical(calib, camera, {method, 0.0});
    const auto rep = reconstruct_files(*engine, camera, captures, bo);
    std::cout << "  " << classical_method_name(method) << ": " << rep.ms_per_capture << " ms per capture\n";
  }
  const bool bf16 = resolve_precision("auto") == Precision::bf16;
  std::cout << "  precision: " << describe_precision(bf16 ? Precision::bf16 : Precision::fp32) << "\n";
  for (const auto& [method, path] : shipped_models()) {
    auto model = load_model_file(path);
    InferenceLevers levers;
    levers.bf16 = bf16;
    // The model's own preprocessing (its light-level centring, say) unless --camera names one.
    const auto& model_camera = r.count("camera") ? camera : model.camera;
    auto engine = make_flatnet(model.generator, model_camera, levers, method);
    BatchOptions bo;
    bo.out = out / "recon" / method;
    bo.label = "infer";
    const auto rep = reconstruct_files(*engine, model_camera, captures, bo);
    std::cout << "  " << method << ": " << rep.ms_per_capture << " ms per capture (" << path.filename().string()
              << ")\n";
  }

  std::cout << "[3/3] evaluating\n";
  EvalOptions eval_options;
  eval_options.gt = sim.out / "gt";
  eval_options.out = out / "recon";
  eval_options.sheet_rows = 6;
  const auto scores = evaluate(eval_options);
  std::cout << format_table(scores) << "\n"
            << "captures:         " << (sim.out / "meas").string() << " (" << srep.total << ")\n"
            << "reconstructions:  " << (out / "recon").string() << "/<method>\n"
            << "metrics:          " << (out / "recon" / "metrics.csv").string() << "\n"
            << "contact sheet:    " << (out / "recon" / "sheet.png").string() << "\n";
  return 0;
}

}  // namespace flatnet::cli
