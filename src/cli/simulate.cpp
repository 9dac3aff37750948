#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "optics/simulator.hpp"

namespace flatnet::cli {

namespace {
void set_noise(SimulateOptions& s, const std::string& text) {
  if (text != "on" && text != "off") throw std::invalid_argument("must be on or off");
  s.noise = text == "on";
}
std::string noise_text(const SimulateOptions& s) { return s.noise ? "on" : "off"; }
}  // namespace

const FlagTable<SimulateOptions>& simulate_flags() {
  using S = SimulateOptions;
  static const FlagTable<S> rows = {
      {"images", &S::images, "folder of photographs"},
      {"out", &S::out, "dataset folder to write"},
      {"val-fraction", &S::val_fraction, "share of images in the validation lists (0 to 1)"},
      {"seed", &S::seed, "seed for the split and the noise"},
      {"noise", FlagText<S>{set_noise, noise_text}, "on|off: photon and read noise"},
      {"size", &S::size, "scene side in pixels (the camera's)"},
      {"limit", &S::limit, "only the first N images (0: all)", 0, 1e12, "0 or more"},
      {"workers", &S::workers, "simulation threads (0: all cores)", 0, 256, "0 (all cores) to 256"},
      {"only", &S::only, "all|train|val: simulate only that part of the split (e.g. val: a held-out evaluation set)"},
      {"exposure", &S::exposure,
       "scene light relative to the display's, in linear light, in (0, 100] (0.33: a dim set); gt/ shows the dimmed "
       "scene"},
      {"lamp", &S::lamp,
       "add one small lamp per scene (a lamp set; position drawn per image), --lamp-gain x display white"},
      {"lamp-gain", &S::lamp_gain, "the lamp's radiance relative to display white"},
      {"force", &S::force,
       "the folder holds captures made with other settings (simulate.yaml): delete them and rebuild"},
  };
  return rows;
}

namespace {

struct SimulateCamera {
  std::filesystem::path camera;  // empty: the reference camera (camera_from reads the flag)
};

const FlagTable<SimulateCamera>& simulate_camera_flags() {
  static const FlagTable<SimulateCamera> rows = {
      {"camera", &SimulateCamera::camera, "rig .mat or camera .yaml naming one (default: the reference camera)"},
  };
  return rows;
}

}  // namespace

CommandFlags simulate_command_flags() { return command_flags("simulate", simulate_camera_flags(), simulate_flags()); }

int simulate(int argc, char** argv) {
  cxxopts::Options o("flatnet simulate", "Simulate the captures a FlatCam gives of photographs shown on a display.");
  add_flags(o, simulate_camera_flags());
  add_flags(o, simulate_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "simulate", "--images DIR and --out DIR are required");
  SimulateOptions opt;
  read_flags(r, simulate_flags(), opt);
  const auto camera = camera_from(r);
  const auto rig = load_camera_rig(camera);
  opt.camera = std::filesystem::weakly_canonical(simulation_source(camera)).string();
  const auto claim = claim_out(r, opt.out, "simulate", "", "simulate.yaml");
  const auto rep = simulate_dataset(rig, opt);
  std::cout << "simulated " << rep.simulated << " captures (" << rep.skipped << " already done) in " << rep.seconds
            << " s: " << (rep.simulated > 0 ? rep.simulated / rep.seconds : 0.0) << " captures/s\n"
            << "lists: " << rep.train << " train, " << rep.val << " val in " << opt.out.string() << "\n";
  // Clipped light is lost: a set whose captures mostly clip teaches a network a sensor that saturates.
  if (rep.clipped > 0)
    std::cerr << "simulate: warning: " << rep.clipped << " of " << rep.simulated << " captures have over "
              << 100 * kClippedShare << " % of their pixels at full scale (clipped: that light is lost)"
              << (2 * rep.clipped > rep.simulated
                      ? "; the scenes are brighter than this camera's light unit holds: lower --exposure (now " +
                            std::to_string(opt.exposure) + "; it scales the scenes' light) until this warning goes"
                      : std::string("; bright scenes clip, as they would on the camera"))
              << "\n";
  return 0;
}

}  // namespace flatnet::cli
