#include "core/precision.hpp"

#include <atomic>
#include <fstream>
#include <mutex>
#include <set>
#include <sstream>

#include <ATen/Context.h>
#include <ATen/autocast_mode.h>
#include <oneapi/dnnl/dnnl.h>
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

namespace {
// oneDNN's ISA masks (dnnl_cpu_isa_t): each ISA's value holds the bits of those below it.
bool isa_has(unsigned isa, unsigned level) { return (isa & level) == level; }

std::string isa_name(unsigned isa) {
  const std::pair<unsigned, const char*> names[] = {{dnnl_cpu_isa_avx512_core_amx, "avx512_core_amx"},
                                                    {dnnl_cpu_isa_avx512_core_bf16, "avx512_core_bf16"},
                                                    {dnnl_cpu_isa_avx512_core_vnni, "avx512_core_vnni"},
                                                    {dnnl_cpu_isa_avx512_core, "avx512_core"},
                                                    {dnnl_cpu_isa_avx2_vnni, "avx2_vnni"},
                                                    {dnnl_cpu_isa_avx2, "avx2"},
                                                    {dnnl_cpu_isa_avx, "avx"},
                                                    {dnnl_cpu_isa_sse41, "sse41"}};
  for (const auto& [level, name] : names)
    if (isa_has(isa, level)) return name;
  return "";
}
}  // namespace

CpuFeatures with_onednn_isa(CpuFeatures cpu, unsigned isa) {
  cpu.onednn_isa = isa_name(isa);
  if (cpu.onednn_isa.empty()) return cpu;  // oneDNN says nothing it knows: keep the flags
  const bool had = cpu.avx512_core || cpu.avx512_bf16 || cpu.amx_bf16;
  if (!isa_has(isa, dnnl_cpu_isa_avx512_core_amx)) cpu.amx_bf16 = false;
  if (!isa_has(isa, dnnl_cpu_isa_avx512_core_bf16)) cpu.avx512_bf16 = false;
  cpu.onednn_bf16 = isa_has(isa, dnnl_cpu_isa_avx512_core);
  if (!cpu.onednn_bf16) cpu.avx512f = cpu.avx512_core = false;
  cpu.onednn_capped = had && !(cpu.avx512_core || cpu.avx512_bf16 || cpu.amx_bf16);
  return cpu;
}

const CpuFeatures& cpu_features() {
  static const CpuFeatures features = [] {
    std::ifstream in("/proc/cpuinfo");
    std::stringstream text;
    text << in.rdbuf();
    return with_onednn_isa(parse_cpuinfo(text.str()), static_cast<unsigned>(dnnl_get_effective_cpu_isa()));
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
  if (onednn_capped) s += " [oneDNN capped at " + onednn_isa + "]";
  return s;
}

Precision resolve_precision(const std::string& choice, const CpuFeatures& cpu, const std::string& what) {
  if (choice == "fp32") return Precision::fp32;
  if (choice == "bf16") return Precision::bf16;
  if (choice == "auto") return cpu.native_bf16() ? Precision::bf16 : Precision::fp32;
  throw Error(what + ": expected auto, fp32 or bf16, got '" + unmarked(choice) + "'");
}

Precision resolve_precision(const std::string& choice, const std::string& what) {
  return resolve_precision(choice, cpu_features(), what);
}

std::string describe_precision(Precision p, const CpuFeatures& cpu) {
  if (p == Precision::fp32) return "fp32";
  if (cpu.native_bf16()) return "bf16 (" + cpu.bf16_engine() + ")";
  if (cpu.onednn_bf16) return "bf16 (emulated by oneDNN: about 3x slower than fp32 on this CPU)";
  return "bf16 (LibTorch's own kernels: oneDNN has no bf16 on " +
         (cpu.onednn_isa.empty() ? std::string("this CPU") : cpu.onednn_isa) +
         "; tens of times slower than fp32, which --precision fp32 or auto runs)";
}

namespace {
std::atomic<int> g_bf16_scopes{0};
bool g_mkldnn_before = true;
std::mutex g_bf16_scope_mutex;
}  // namespace

void use_bf16_kernels_for_process() {
  if (cpu_features().onednn_bf16) return;
  std::lock_guard<std::mutex> lock(g_bf16_scope_mutex);
  at::globalContext().setUserEnabledMkldnn(false);
  g_mkldnn_before = false;  // open scopes restore "off" too
}

Bf16KernelScope::Bf16KernelScope(bool enabled) : active_(enabled && !cpu_features().onednn_bf16) {
  if (!active_) return;
  std::lock_guard<std::mutex> lock(g_bf16_scope_mutex);
  if (g_bf16_scopes++ == 0) {
    g_mkldnn_before = at::globalContext().userEnabledMkldnn();
    at::globalContext().setUserEnabledMkldnn(false);
  }
}

Bf16KernelScope::~Bf16KernelScope() {
  if (!active_) return;
  std::lock_guard<std::mutex> lock(g_bf16_scope_mutex);
  if (--g_bf16_scopes == 0) at::globalContext().setUserEnabledMkldnn(g_mkldnn_before);
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
  use_bf16_kernels_for_process();  // autocast means training: its backward pass runs after this guard
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
