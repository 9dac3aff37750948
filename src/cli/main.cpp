// flatnet: lensless FlatCam reconstruction and mask design. This file only dispatches.
#include <cxxopts.hpp>
#include <filesystem>
#include <iostream>
#include <map>

#include <c10/util/Exception.h>  // c10::Error: LibTorch's exceptions become one line too

#include "cli/commands.hpp"
#include "core/blas.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "train/options.hpp"

namespace {

const std::map<std::string, std::pair<int (*)(int, char**), const char*>> kCommands = {
    {"simulate", {flatnet::cli::simulate, "simulate display captures of photographs with a camera rig"}},
    {"calibrate", {flatnet::cli::calibrate, "estimate a calibration (P, Q) from separable pattern captures"}},
    {"recon", {flatnet::cli::recon, "classical reconstruction (Tikhonov, TV) of raw captures"}},
    {"eval", {flatnet::cli::eval, "PSNR/SSIM/NIQE of reconstructions against ground truth, with a contact sheet"}},
    {"report",
     {flatnet::cli::report, "every method on every held-out set: the thesis's table and figures (report.md)"}},
    {"train", {flatnet::cli::train, "train a FlatNet reconstruction network (resumable)"}},
    {"infer", {flatnet::cli::infer, "reconstruct raw captures with a trained model"}},
    {"export", {flatnet::cli::export_model, "checkpoint -> model file, or model -> PyTorch state_dict"}},
    {"info", {flatnet::cli::info, "what a model file holds: architecture, camera, recipe, training, scores, SHA-256"}},
    {"options", {flatnet::cli::options, "every setting of a trainer's config: default, range, what it does"}},
    {"import", {flatnet::cli::import_model, "PyTorch state_dict (FlatNet-sep names) -> model file"}},
    {"mask", {flatnet::cli::mask, "learn FlatCam masks (train), score them (eval), compare them (report)"}},
    {"cameras", {flatnet::cli::cameras, "list the cameras Aravis can reach (GenICam: USB3 Vision, GigE Vision)"}},
    {"capture", {flatnet::cli::capture, "capture averaged raw frames from a camera (16-bit PNG + JSON sidecar)"}},
    {"capture-dataset", {flatnet::cli::capture_dataset, "display-capture dataset collection (resumable)"}},
    {"capture-calibration",
     {flatnet::cli::capture_calibration, "show and capture the calibration patterns, then calibrate"}},
    {"live", {flatnet::cli::live, "live view: grab, reconstruct (Tikhonov or FlatNet), show with the frame rate"}},
    {"bench", {flatnet::cli::bench, "time the hot paths (scripts/bench_compare.sh compares them with PyTorch)"}},
    {"demo", {flatnet::cli::demo, "simulate, reconstruct and evaluate a few photographs end to end"}},
};

void usage() {
  std::cout << "flatnet " << FLATNET_VERSION << ": lensless FlatCam imaging\n\nusage: flatnet <command> [options]\n\n";
  for (const auto& [name, entry] : kCommands)
    std::cout << "  " << name << std::string(name.size() < 21 ? 21 - name.size() : 1, ' ') << entry.second << "\n";
  std::cout << "\n'flatnet <command> --help' lists a command's options.\n";
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || std::string(argv[1]) == "-h" || std::string(argv[1]) == "--help") {
    usage();
    return argc < 2 ? 2 : 0;
  }
  const std::string command = argv[1];
  if (command == "--version" || command == "version") {
    std::cout << "flatnet " << FLATNET_VERSION << "\n";
    return 0;
  }
  auto it = kCommands.find(command);
  if (it == kCommands.end()) {
    std::cerr << "flatnet: unknown command '" << command << "' (run 'flatnet --help')\n";
    return 2;
  }
  flatnet::register_option_tables();       // every setting's range, before any config is read
  flatnet::select_openblas_kernels(argv);  // may re-execute this program once (core/blas.hpp)
  flatnet::keep_freed_memory();
  try {
    return it->second.first(argc - 1, argv + 1);
  } catch (const flatnet::Error& e) {
    std::cerr << "flatnet " << command << ": error: " << flatnet::printable(e.render(flatnet::cli::flag_or_key))
              << "\n";
  } catch (const cxxopts::exceptions::exception& e) {
    std::cerr << "flatnet " << command << ": error: " << flatnet::printable(e.what()) << "\n";
  } catch (const std::filesystem::filesystem_error& e) {  // "PATH: reason", as flatnet's own errors
    std::cerr << "flatnet " << command << ": error: "
              << flatnet::printable(e.path1().string() + (e.path2().empty() ? "" : " -> " + e.path2().string())) << ": "
              << e.code().message() << "\n";
  } catch (const c10::Error& e) {
    std::cerr << "flatnet " << command << ": internal error: " << flatnet::printable(e.what_without_backtrace())
              << "\n";
    return 1;
  } catch (const std::exception& e) {
    std::cerr << "flatnet " << command << ": error: " << flatnet::printable(e.what()) << "\n";
  }
  return 2;
}
