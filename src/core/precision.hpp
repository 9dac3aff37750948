#pragma once
// Numeric precision chosen at run time. Machines differ: Intel AMX and AVX512-BF16 run bfloat16
// convolutions and GEMMs natively (several times faster than fp32); on other AVX-512 CPUs oneDNN
// emulates bf16 (~3x slower than fp32); below AVX-512 oneDNN has no bf16 convolution at all, and
// LibTorch's own (slow) kernels run it instead. `auto` therefore means bf16 only where it is native.
// What the CPU can do is read from /proc/cpuinfo and then from oneDNN itself, so that a cap
// (ONEDNN_MAX_CPU_ISA=AVX2, or DNNL_MAX_CPU_ISA) and a CPU without the kernels are treated alike.
#include <string>

namespace flatnet {

enum class Precision { fp32, bf16 };

// What this CPU offers, read from /proc/cpuinfo's flags (Linux; elsewhere nothing).
struct CpuFeatures {
  std::string model;  // "Intel(R) Xeon(R) Processor"
  bool avx512f = false;
  bool avx512_core = false;    // F, CD, BW, DQ and VL: what OpenBLAS's SkylakeX kernels need
  bool avx512_bf16 = false;    // AVX512-BF16: vdpbf16ps
  bool amx_bf16 = false;       // AMX tiles with bf16
  std::string onednn_isa;      // oneDNN's effective ISA ("avx2", "avx512_core_bf16", ...); "" unknown
  bool onednn_capped = false;  // that ISA is below what the CPU's flags offer (ONEDNN_MAX_CPU_ISA)
  bool onednn_bf16 = true;     // oneDNN runs bf16 convolutions here (its ISA is AVX-512 or above)
  bool native_bf16() const { return avx512_bf16 || amx_bf16; }
  // "AMX", "AVX512-BF16" or "emulated": how bf16 runs here.
  std::string bf16_engine() const;
  // "Intel(R) Xeon(R) Processor; avx512f avx512_bf16 amx_bf16" (for benchmark reports).
  std::string summary() const;
};
const CpuFeatures& cpu_features();
// Parses a /proc/cpuinfo text (exposed for tests).
CpuFeatures parse_cpuinfo(const std::string& text);
// The features as oneDNN will use them: `isa` is dnnl_get_effective_cpu_isa()'s value (bit masks,
// oneDNN's dnnl_cpu_isa_t). Flags above the effective ISA are cleared (exposed for tests).
CpuFeatures with_onednn_isa(CpuFeatures cpu, unsigned isa);
// "auto" | "fp32" | "bf16" -> a precision; auto is bf16 where the CPU has it natively. `what`
// names the option in errors (--precision, train.precision).
Precision resolve_precision(const std::string& choice, const std::string& what = "--precision");
Precision resolve_precision(const std::string& choice, const CpuFeatures& cpu, const std::string& what);
// "bf16 (AMX)", "bf16 (emulated: slow on this CPU)", "fp32".
std::string describe_precision(Precision p, const CpuFeatures& cpu = cpu_features());

// While alive, bf16 convolutions run where they can: where oneDNN has no bf16 kernels (below
// AVX-512, or capped), LibTorch's oneDNN path is switched off so that its own kernels run them
// (LibTorch 1.13 asks cpuinfo, not oneDNN, and would call oneDNN anyway: "could not create a
// primitive descriptor iterator"). Nested and thread-safe by count; a no-op where oneDNN has bf16.
// The same for the rest of the process: bf16 training, whose backward pass runs outside any scope.
void use_bf16_kernels_for_process();
class Bf16KernelScope {
 public:
  explicit Bf16KernelScope(bool enabled = true);
  ~Bf16KernelScope();
  Bf16KernelScope(const Bf16KernelScope&) = delete;
  Bf16KernelScope& operator=(const Bf16KernelScope&) = delete;

 private:
  bool active_;
};

// Asks the kernel for the AMX tile state (arch_prctl ARCH_REQ_XCOMP_PERM, Linux >= 5.16). oneDNN
// asks too; doing it up front makes a refusal visible. Returns false where AMX is absent or refused.
bool request_amx_permission();

// bf16 autocast on the CPU for the current thread while alive (torch.autocast('cpu',
// torch.bfloat16) in C++): convolutions and matmuls run in bf16, parameters stay fp32 and get
// fp32 gradients. Where oneDNN has no bf16 kernels, the first enabled guard switches LibTorch's
// oneDNN path off for the process (use_bf16_kernels_for_process): the backward pass comes later. Leaving the outermost
// guard clears the cast cache (stale casts of updated weights would otherwise be reused). Enabled = false makes it a
// no-op.
class AutocastGuard {
 public:
  explicit AutocastGuard(bool enabled);
  ~AutocastGuard();
  AutocastGuard(const AutocastGuard&) = delete;
  AutocastGuard& operator=(const AutocastGuard&) = delete;

 private:
  bool enabled_, prev_enabled_ = false;
  int prev_dtype_ = 0;
};

// Switches autocast off for the current thread while alive (for stages that must stay fp32 inside
// an autocast region: the inversion's wide-range matmuls, losses).
class AutocastOffGuard {
 public:
  AutocastOffGuard();
  ~AutocastOffGuard();
  AutocastOffGuard(const AutocastOffGuard&) = delete;
  AutocastOffGuard& operator=(const AutocastOffGuard&) = delete;

 private:
  bool prev_enabled_;
};

}  // namespace flatnet
