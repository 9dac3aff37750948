#include "core/precision.hpp"

#include <fstream>
#include <set>
#include <sstream>

#include <ATen/autocast_mode.h>
#if defined(__linux__)
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include "core/error.hpp"

namespace flatnet {

CpuFeatures parse_cpuinfo(const std::string& text) {
  CpuFeatures f;
  std::istringstream in(text);
  std::string line;
  bool flags_seen = false;
  while (std::getline(in, line)) {
    const auto colon = line.find(':');
    if (colon == std::string::npos) continue;
    auto key = line.substr(0, colon);
    key.erase(key.find_last_not_of(" \t") + 1);
    const auto value = colon + 2 <= line.size() ? line.substr(colon + 2) : std::string();
    if (key == "model name" && f.model.empty()) f.model = value;
    if (key == "flags" && !flags_seen) {  // the first processor's flags (all cores are alike)
      flags_seen = true;
      std::istringstream words(value);
      std::set<std::string> flags;
      for (std::string w; words >> w;) flags.insert(w);
      f.avx512f = flags.count("avx512f") > 0;
      f.avx512_core = f.avx512f && flags.count("avx512cd") && flags.count("avx512bw") && flags.count("avx512dq") &&
                      flags.count("avx512vl");
      f.avx512_bf16 = flags.count("avx512_bf16") > 0;
      f.amx_bf16 = flags.count("amx_bf16") > 0;
    }
  }
  return f;
}

const CpuFeatures& cpu_features() {
  static const CpuFeatures features = [] {
    std::ifstream in("/proc/cpuinfo");
    std::stringstream text;
    text << in.rdbuf();
    return parse_cpuinfo(text.str());
  }();
  return features;
}

std::string CpuFeatures::bf16_engine() const {
  if (amx_bf16) return "AMX";
  if (avx512_bf16) return "AVX512-BF16";
  return "emulated";
}

std::string CpuFeatures::summary() const {
  std::string s = model.empty() ? "unknown CPU" : model;
  s += ";";
  if (avx512f) s += " avx512f";
  if (avx512_bf16) s += " avx512_bf16";
  if (amx_bf16) s += " amx_bf16";
  if (!avx512f && !avx512_bf16 && !amx_bf16) s += " (no AVX-512, no native bf16)";
  return s;
}

Precision resolve_precision(const std::string& choice, const CpuFeatures& cpu, const std::string& what) {
  if (choice == "fp32") return Precision::fp32;
  if (choice == "bf16") return Precision::bf16;
  if (choice == "auto") return cpu.native_bf16() ? Precision::bf16 : Precision::fp32;
  throw Error(what + ": expected auto, fp32 or bf16, got '" + choice + "'");
}

Precision resolve_precision(const std::string& choice, const std::string& what) {
  return resolve_precision(choice, cpu_features(), what);
}

std::string describe_precision(Precision p, const CpuFeatures& cpu) {
  if (p == Precision::fp32) return "fp32";
  if (cpu.native_bf16()) return "bf16 (" + cpu.bf16_engine() + ")";
  return "bf16 (emulated: about 3x slower than fp32 on this CPU)";
}

bool request_amx_permission() {
#if defined(__linux__) && defined(SYS_arch_prctl)
  if (!cpu_features().amx_bf16) return false;
  constexpr int kArchReqXcompPerm = 0x1023, kXfeatureXtiledata = 18;
  return syscall(SYS_arch_prctl, kArchReqXcompPerm, kXfeatureXtiledata) == 0;
#else
  return false;
#endif
}

AutocastGuard::AutocastGuard(bool enabled) : enabled_(enabled) {
  if (!enabled_) return;
  prev_enabled_ = at::autocast::is_cpu_enabled();
  prev_dtype_ = static_cast<int>(at::autocast::get_autocast_cpu_dtype());
  at::autocast::set_cpu_enabled(true);
  at::autocast::set_autocast_cpu_dtype(at::kBFloat16);
  at::autocast::increment_nesting();
}

AutocastGuard::~AutocastGuard() {
  if (!enabled_) return;
  if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
  at::autocast::set_cpu_enabled(prev_enabled_);
  at::autocast::set_autocast_cpu_dtype(static_cast<at::ScalarType>(prev_dtype_));
}

AutocastOffGuard::AutocastOffGuard() : prev_enabled_(at::autocast::is_cpu_enabled()) {
  at::autocast::set_cpu_enabled(false);
}

AutocastOffGuard::~AutocastOffGuard() { at::autocast::set_cpu_enabled(prev_enabled_); }

}  // namespace flatnet
