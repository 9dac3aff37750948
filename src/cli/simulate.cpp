#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "optics/simulator.hpp"

namespace flatnet::cli {

int simulate(int argc, char** argv) {
  cxxopts::Options o("flatnet simulate", "Simulate the captures a FlatCam gives of photographs shown on a display.");
  o.add_options()("camera", "rig .mat or camera .yaml naming one (default: the reference camera)",
                  cxxopts::value<std::string>())("images", "folder of photographs", cxxopts::value<std::string>())(
      "out", "dataset folder to write", cxxopts::value<std::string>())(
      "val-fraction", "share of images in the validation lists", cxxopts::value<double>()->default_value("0.1"))(
      "seed", "seed for the split and the noise", cxxopts::value<uint64_t>()->default_value("0"))(
      "noise", "on|off: photon and read noise", cxxopts::value<std::string>()->default_value("on"))(
      "size", "scene side in pixels", cxxopts::value<int64_t>()->default_value("256"))(
      "limit", "only the first N images (0: all)", cxxopts::value<int64_t>()->default_value("0"))(
      "workers", "simulation threads (default: all cores)", cxxopts::value<int>()->default_value("0"))(
      "only", "all|train|val: simulate only that part of the split (e.g. val: a held-out evaluation set)",
      cxxopts::value<std::string>()->default_value("all"))(
      "exposure",
      "scene light relative to the display's, in linear light (0.33: a dim set); gt/ shows the dimmed scene",
      cxxopts::value<double>()->default_value("1"))(
      "lamp", "add one small lamp per scene (a lamp set; position drawn per image), --lamp-gain x display white")(
      "lamp-gain", "the lamp's radiance relative to display white", cxxopts::value<double>()->default_value("20"))(
      "force", "the folder holds captures made with other settings (simulate.yaml): delete them and rebuild");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "simulate", "--images DIR and --out DIR are required");
  const auto noise = r["noise"].as<std::string>();
  require(noise == "on" || noise == "off", "--noise", "must be on or off");
  const auto camera = camera_from(r);
  const auto rig = load_camera_rig(camera);
  SimulateOptions opt;
  opt.images = r["images"].as<std::string>();
  opt.out = r["out"].as<std::string>();
  opt.val_fraction = r["val-fraction"].as<double>();
  opt.seed = r["seed"].as<uint64_t>();
  opt.noise = noise == "on";
  opt.size = r["size"].as<int64_t>();
  opt.limit = r["limit"].as<int64_t>();
  opt.workers = r["workers"].as<int>();
  opt.exposure = r["exposure"].as<double>();
  opt.only = r["only"].as<std::string>();
  opt.lamp = r.count("lamp") > 0;
  opt.lamp_gain = r["lamp-gain"].as<double>();
  opt.camera = std::filesystem::weakly_canonical(simulation_source(camera)).string();
  opt.force = r.count("force") > 0;
  const auto claim = claim_out(r, opt.out, "simulate", "", "simulate.yaml");
  const auto rep = simulate_dataset(rig, opt);
  std::cout << "simulated " << rep.simulated << " captures (" << rep.skipped << " already done) in " << rep.seconds
            << " s: " << (rep.simulated > 0 ? rep.simulated / rep.seconds : 0.0) << " captures/s\n"
            << "lists: " << rep.train << " train, " << rep.val << " val in " << opt.out.string() << "\n";
  return 0;
}

}  // namespace flatnet::cli
