#include "nn/onednn_conv.hpp"

#include <ATen/autocast_mode.h>
#include <oneapi/dnnl/dnnl.hpp>

#include <atomic>
#include <mutex>
#include <tuple>
#include <unordered_map>

#include "core/error.hpp"
#include "core/precision.hpp"

namespace flatnet {

namespace {

using dt = dnnl::memory::data_type;
using tag = dnnl::memory::format_tag;

std::atomic<int64_t> built_count{0};

dnnl::engine& cpu_engine() {
  static dnnl::engine engine(dnnl::engine::kind::cpu, 0);
  return engine;
}

// One in-order stream per calling thread, made once rather than on every convolution.
dnnl::stream& cpu_stream() {
  thread_local dnnl::stream stream(cpu_engine());
  return stream;
}

// Buffers for the reordered operands of one convolution pass, kept per thread and grown as needed.
// A fresh 16-33 MB buffer per pass page-faulted in each reorder (70 ms of reorders in a 570 ms step
// under the AVX2 cap, where the copies themselves take about 15).
enum class Scratch { weights = 0, src = 1, diff_dst = 2, primitive = 3, count = 4 };

void* scratch(Scratch slot, size_t bytes) {
  thread_local std::array<torch::Tensor, static_cast<size_t>(Scratch::count)> buffers;
  auto& buffer = buffers[static_cast<size_t>(slot)];
  if (!buffer.defined() || static_cast<size_t>(buffer.numel()) < bytes)
    buffer = torch::empty({static_cast<int64_t>(bytes)}, torch::TensorOptions().dtype(torch::kUInt8));
  return buffer.data_ptr();
}

// Primitives are made once and shared by every thread that trains (two ranks in one process, in the
// distributed tests), so each is made with a scratchpad its caller owns: oneDNN's own would be one
// buffer for concurrent executions. This attribute asks for that; run() hands it over.
dnnl::primitive_attr user_scratchpad() {
  dnnl::primitive_attr attr;
  attr.set_scratchpad_mode(dnnl::scratchpad_mode::user);
  return attr;
}

// Executes a primitive made with user_scratchpad() on this thread's stream, with the scratchpad its
// descriptor asks for from this thread's buffer, and waits for it.
void run(const dnnl::primitive& primitive, std::unordered_map<int, dnnl::memory> args) {
  const_dnnl_primitive_desc_t pd = nullptr;
  dnnl::error::wrap_c_api(dnnl_primitive_get_primitive_desc(primitive.get(), &pd), "no primitive descriptor");
  const dnnl::memory::desc pad(*dnnl_primitive_desc_query_md(pd, dnnl_query_scratchpad_md, 0));
  if (pad.get_size() > 0)
    args[DNNL_ARG_SCRATCHPAD] = dnnl::memory(pad, cpu_engine(), scratch(Scratch::primitive, pad.get_size()));
  primitive.execute(cpu_stream(), args);
  cpu_stream().wait();
}

// The plan for `key`, made by `make` on first asking and kept for the process (threads share it);
// nullptr, kept too, where oneDNN has no kernel for it (`make` throws dnnl::error or returns nullptr).
template <class Key, class Plan, class Make>
Plan* kept_plan(std::map<Key, std::unique_ptr<Plan>>& plans, std::mutex& mutex, const Key& key, Make make) {
  std::lock_guard<std::mutex> lock(mutex);
  const auto found = plans.find(key);
  if (found != plans.end()) return found->second.get();
  std::unique_ptr<Plan> plan;
  try {
    plan = make();
  } catch (const dnnl::error&) {
    plan.reset();  // LibTorch's operators run it
  }
  return (plans[key] = std::move(plan)).get();
}

}  // namespace

struct OneDnnConv::Plan {
  dnnl::convolution_forward primitive;
  dnnl::memory::desc src, dst;
  dnnl::memory weights, bias;  // weights in the kernel's own layout (reordered once)
  std::array<int64_t, 4> out_shape;
};

OneDnnConv::OneDnnConv(const torch::Tensor& weight, const torch::Tensor& bias, const OneDnnConvOptions& options)
    : weight_(
          weight.detach().to(torch::kBFloat16).contiguous(at::MemoryFormat::ChannelsLast)),  // no copy after the levers
      opt_(options) {
  TORCH_CHECK(weight_.dim() == 4, "OneDnnConv: a 4-D weight expected");
  in_channels_ = weight_.size(1);
  out_channels_ = weight_.size(0);
  bias_ = bias.defined() ? bias.detach().to(torch::kFloat32).contiguous() : torch::zeros({out_channels_});
  TORCH_CHECK(bias_.numel() == out_channels_, "OneDnnConv: one bias per output channel expected");
  ++built_count;
}

int64_t OneDnnConv::built() { return built_count; }

OneDnnConv::~OneDnnConv() = default;

OneDnnConv::Plan& OneDnnConv::plan_for(int64_t b, int64_t h, int64_t w) {
  auto& slot = plans_[{b, h, w}];
  if (slot) return *slot;
  const int64_t o = out_channels_, i = in_channels_, kh = weight_.size(2), kw = weight_.size(3);
  const int64_t s = opt_.stride, p = opt_.padding;
  const int64_t oh = (h + 2 * p - kh) / s + 1, ow = (w + 2 * p - kw) / s + 1;
  auto plan = std::make_unique<Plan>();
  plan->src = dnnl::memory::desc({b, i, h, w}, dt::bf16, tag::nhwc);
  plan->dst = dnnl::memory::desc({b, o, oh, ow}, dt::bf16, tag::nhwc);
  const dnnl::memory::desc any_weights({o, i, kh, kw}, dt::bf16, tag::any), bias_desc({o}, dt::f32, tag::a);
  dnnl::primitive_attr attr;
  if (opt_.relu) {
    dnnl::post_ops ops;
    ops.append_eltwise(1.0f, dnnl::algorithm::eltwise_relu, 0.0f, 0.0f);
    attr.set_post_ops(ops);
  }
  const dnnl::convolution_forward::desc desc(dnnl::prop_kind::forward_inference, dnnl::algorithm::convolution_direct,
                                             plan->src, any_weights, bias_desc, plan->dst, {s, s}, {p, p}, {p, p});
  const dnnl::convolution_forward::primitive_desc pd(desc, attr, cpu_engine());
  plan->primitive = dnnl::convolution_forward(pd);
  auto& stream = cpu_stream();
  // The module's weights as they lie in memory: {O,kh,kw,I} (channels-last).
  dnnl::memory user_weights({{o, i, kh, kw}, dt::bf16, tag::ohwi}, cpu_engine(), weight_.data_ptr());
  plan->weights = dnnl::memory(pd.weights_desc(), cpu_engine());
  dnnl::reorder(user_weights, plan->weights)
      .execute(stream, user_weights, plan->weights);  // -> the kernel's blocked layout
  plan->bias = dnnl::memory(bias_desc, cpu_engine(), bias_.data_ptr());
  stream.wait();
  plan->out_shape = {b, o, oh, ow};
  slot = std::move(plan);
  return *slot;
}

torch::Tensor OneDnnConv::operator()(const torch::Tensor& input) {
  TORCH_CHECK(input.dim() == 4 && input.size(1) == in_channels_, "OneDnnConv: {B,", in_channels_,
              ",H,W} input expected, got ", input.sizes());
  const auto x = input.to(torch::kBFloat16).contiguous(at::MemoryFormat::ChannelsLast);
  Plan& plan = plan_for(x.size(0), x.size(2), x.size(3));
  auto y = torch::empty({plan.out_shape[0], plan.out_shape[1], plan.out_shape[2], plan.out_shape[3]},
                        x.options().memory_format(at::MemoryFormat::ChannelsLast));
  dnnl::memory src(plan.src, cpu_engine(), x.data_ptr()), dst(plan.dst, cpu_engine(), y.data_ptr());
  auto& stream = cpu_stream();
  plan.primitive.execute(
      stream, {{DNNL_ARG_SRC, src}, {DNNL_ARG_WEIGHTS, plan.weights}, {DNNL_ARG_BIAS, plan.bias}, {DNNL_ARG_DST, dst}});
  stream.wait();
  return y;
}

namespace {

struct MatmulPlan {
  dnnl::matmul primitive;
  dnnl::memory::desc a, b, c;
};

// A {batch,rows,cols} operand as oneDNN reads it: row-major, or (transposed) the transpose of a
// row-major {batch,cols,rows} tensor, read in place instead of copied.
dnnl::memory::desc operand_desc(int64_t batch, int64_t rows, int64_t cols, bool transposed, dt type) {
  if (!transposed) return dnnl::memory::desc({batch, rows, cols}, type, tag::abc);
  return dnnl::memory::desc({batch, rows, cols}, type, dnnl::memory::dims{rows * cols, 1, rows});
}

// Made once per shape (batch of A, of B, M, K, N, which operands are transposed) and operand type,
// shared by the threads that ask. The result is fp32 either way.
MatmulPlan& matmul_plan(int64_t batch_a, int64_t batch_b, int64_t m, int64_t k, int64_t n, bool a_t, bool b_t,
                        GemmOperands operands) {
  static std::mutex mutex;
  static std::map<std::array<int64_t, 8>, std::unique_ptr<MatmulPlan>> plans;
  std::lock_guard<std::mutex> lock(mutex);
  auto& slot = plans[{batch_a, batch_b, m, k, n, a_t, b_t, static_cast<int64_t>(operands)}];
  if (!slot) {
    auto plan = std::make_unique<MatmulPlan>();
    const int64_t batch = std::max(batch_a, batch_b);
    const auto type = operands == GemmOperands::bf16 ? dt::bf16 : dt::f32;
    plan->a = operand_desc(batch_a, m, k, a_t, type);
    plan->b = operand_desc(batch_b, k, n, b_t, type);
    plan->c = dnnl::memory::desc({batch, m, n}, dt::f32, tag::abc);
    const dnnl::matmul::desc desc(plan->a, plan->b, plan->c);
    plan->primitive = dnnl::matmul(dnnl::matmul::primitive_desc(desc, user_scratchpad(), cpu_engine()));
    slot = std::move(plan);
  }
  return *slot;
}

// In the operands' type and row-major, or the transpose of a row-major tensor (a view as
// x.transpose(1, 2) gives), which oneDNN reads in place; anything else is copied row-major first.
std::pair<torch::Tensor, bool> gemm_operand(const torch::Tensor& x, GemmOperands operands) {
  auto t = x.to(operands == GemmOperands::bf16 ? torch::kBFloat16 : torch::kFloat32);
  if (t.is_contiguous()) return {t, false};
  if (t.transpose(1, 2).is_contiguous()) return {t, true};
  return {t.contiguous(), false};
}

std::atomic<uint64_t> onednn_work{0};  // FLOPs, onednn_flops()

}  // namespace

uint64_t onednn_flops() { return onednn_work.load(); }

torch::Tensor onednn_bmm(const torch::Tensor& a_in, const torch::Tensor& b_in, GemmOperands operands) {
  RECORD_FUNCTION("flatnet::onednn_bmm", c10::ArrayRef<c10::IValue>{});
  TORCH_CHECK(a_in.dim() == 3 && b_in.dim() == 3 && a_in.size(2) == b_in.size(1) &&
                  (a_in.size(0) == b_in.size(0) || a_in.size(0) == 1 || b_in.size(0) == 1),
              "onednn_bmm: {batch,M,K} x {batch,K,N} expected, got ", a_in.sizes(), " and ", b_in.sizes());
  TORCH_CHECK(operands == GemmOperands::fp32 || cpu_features().native_bf16(),
              "onednn_bmm: bf16 operands need a CPU that runs bf16 natively (AVX512-BF16 or AMX)");
  const auto [a, a_t] = gemm_operand(a_in, operands);
  const auto [b, b_t] = gemm_operand(b_in, operands);
  const int64_t m = a.size(1), k = a.size(2), n = b.size(2);
  const auto& plan = matmul_plan(a.size(0), b.size(0), m, k, n, a_t, b_t, operands);
  auto c = torch::empty({std::max(a.size(0), b.size(0)), m, n}, a.options().dtype(torch::kFloat32));
  dnnl::memory am(plan.a, cpu_engine(), a.data_ptr()), bm(plan.b, cpu_engine(), b.data_ptr()),
      cm(plan.c, cpu_engine(), c.data_ptr());
  run(plan.primitive, {{DNNL_ARG_SRC, am}, {DNNL_ARG_WEIGHTS, bm}, {DNNL_ARG_DST, cm}});
  onednn_work += static_cast<uint64_t>(2 * c.size(0) * m * k * n);
  return c;
}

namespace {

class OneDnnMatmulFunction : public torch::autograd::Function<OneDnnMatmulFunction> {
 public:
  static torch::Tensor forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& a, const torch::Tensor& b,
                               GemmOperands operands) {
    // Rounded once, for the product and both gradients (fp32 operands: a and b themselves).
    const auto type = operands == GemmOperands::bf16 ? torch::kBFloat16 : torch::kFloat32;
    const auto a_in = a.to(type), b_in = b.to(type);
    ctx->save_for_backward({a_in, b_in});  // their type is the operands', their batches a's and b's
    return onednn_bmm(a_in, b_in, operands);
  }
  static torch::autograd::tensor_list backward(torch::autograd::AutogradContext* ctx,
                                               torch::autograd::tensor_list grads) {
    const auto saved = ctx->get_saved_variables();
    const auto &a = saved[0], &b = saved[1];
    const auto operands = a.scalar_type() == torch::kBFloat16 ? GemmOperands::bf16 : GemmOperands::fp32;
    // {batch,M,N}; rounded to bf16 once here rather than in each product below
    const auto grad =
        operands == GemmOperands::bf16 ? grads[0].to(torch::kBFloat16).contiguous() : grads[0].contiguous();
    auto reduce_to = [](torch::Tensor g, int64_t batch) { return batch == 1 && g.size(0) > 1 ? g.sum(0, true) : g; };
    torch::Tensor grad_a, grad_b;
    if (ctx->needs_input_grad(0)) grad_a = reduce_to(onednn_bmm(grad, b.transpose(1, 2), operands), a.size(0));
    if (ctx->needs_input_grad(1)) grad_b = reduce_to(onednn_bmm(a.transpose(1, 2), grad, operands), b.size(0));
    return {grad_a, grad_b, torch::Tensor()};
  }
};

}  // namespace

torch::Tensor onednn_matmul_autograd(const torch::Tensor& a, const torch::Tensor& b, GemmOperands operands) {
  return OneDnnMatmulFunction::apply(a, b, operands);
}

namespace {

// Forward and backward primitives for one shape, type and activation, made once and shared. ReLU
// rides in the batch norm itself (fuse_norm_relu, its mask in the workspace); swish is an eltwise
// primitive after it, whose backward reads the batch norm's output (saved).
struct NormPlan {
  dnnl::batch_normalization_forward::primitive_desc forward_pd;
  dnnl::batch_normalization_forward forward;
  dnnl::batch_normalization_backward backward;
  dnnl::eltwise_forward swish_forward;    // swish only
  dnnl::eltwise_backward swish_backward;  // swish only
  dnnl::memory::desc data, stats;
};

// nullptr where oneDNN has no kernel for this type here (bf16 below AVX-512).
NormPlan* norm_plan(int64_t B, int64_t C, int64_t H, int64_t W, at::ScalarType type, double eps,
                    NormActivation activation) {
  static std::mutex mutex;
  static std::map<std::tuple<int64_t, int64_t, int64_t, int64_t, int, double, int>, std::unique_ptr<NormPlan>> plans;
  const auto key = std::make_tuple(B, C, H, W, static_cast<int>(type), eps, static_cast<int>(activation));
  return kept_plan(plans, mutex, key, [&] {
    auto plan = std::make_unique<NormPlan>();
    plan->data = dnnl::memory::desc({B, C, H, W}, type == at::kBFloat16 ? dt::bf16 : dt::f32, tag::nhwc);
    plan->stats = dnnl::memory::desc({C}, dt::f32, tag::a);
    const bool relu = activation == NormActivation::relu;
    auto flags = dnnl::normalization_flags::use_scale | dnnl::normalization_flags::use_shift;
    if (relu) flags = flags | dnnl::normalization_flags::fuse_norm_relu;
    const auto e = static_cast<float>(eps);
    const auto attr = user_scratchpad();
    plan->forward_pd = dnnl::batch_normalization_forward::primitive_desc(
        dnnl::batch_normalization_forward::desc(dnnl::prop_kind::forward_training, plan->data, e, flags), attr,
        cpu_engine());
    plan->forward = dnnl::batch_normalization_forward(plan->forward_pd);
    plan->backward = dnnl::batch_normalization_backward(dnnl::batch_normalization_backward::primitive_desc(
        dnnl::batch_normalization_backward::desc(dnnl::prop_kind::backward, plan->data, plan->data, e, flags), attr,
        cpu_engine(), plan->forward_pd));
    if (!relu) {  // swish(z) = z sigmoid(z): oneDNN's eltwise_swish with alpha 1
      const auto swish_pd = dnnl::eltwise_forward::primitive_desc(
          dnnl::eltwise_forward::desc(dnnl::prop_kind::forward_training, dnnl::algorithm::eltwise_swish, plan->data,
                                      1.f, 0.f),
          attr, cpu_engine());
      plan->swish_forward = dnnl::eltwise_forward(swish_pd);
      plan->swish_backward = dnnl::eltwise_backward(dnnl::eltwise_backward::primitive_desc(
          dnnl::eltwise_backward::desc(dnnl::algorithm::eltwise_swish, plan->data, plan->data, 1.f, 0.f), attr,
          cpu_engine(), swish_pd));
    }
    return plan;
  });
}

dnnl::memory wrap(const dnnl::memory::desc& desc, const torch::Tensor& t) {
  return dnnl::memory(desc, cpu_engine(), t.data_ptr());
}

class BatchNormActivationFunction : public torch::autograd::Function<BatchNormActivationFunction> {
 public:
  static torch::Tensor forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& x,
                               const torch::Tensor& weight, const torch::Tensor& bias, torch::Tensor running_mean,
                               torch::Tensor running_var, double momentum, double eps, int64_t activation) {
    const int64_t B = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3);
    const auto act = static_cast<NormActivation>(activation);
    auto* plan = norm_plan(B, C, H, W, x.scalar_type(), eps, act);
    TORCH_CHECK(plan, "onednn_batch_norm_activation: no oneDNN kernel for ", x.scalar_type());
    const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    const auto scale = weight.detach().to(torch::kFloat32).contiguous();
    const auto shift = bias.detach().to(torch::kFloat32).contiguous();
    auto normed = torch::empty_like(x, at::MemoryFormat::ChannelsLast);  // ReLU: the output; swish: its input
    auto mean = torch::empty({C}, f32), var = torch::empty({C}, f32);
    torch::Tensor workspace;  // ReLU's mask; swish keeps its input instead
    std::unordered_map<int, dnnl::memory> args{
        {DNNL_ARG_SRC, wrap(plan->data, x)},        {DNNL_ARG_DST, wrap(plan->data, normed)},
        {DNNL_ARG_SCALE, wrap(plan->stats, scale)}, {DNNL_ARG_SHIFT, wrap(plan->stats, shift)},
        {DNNL_ARG_MEAN, wrap(plan->stats, mean)},   {DNNL_ARG_VARIANCE, wrap(plan->stats, var)}};
    if (act == NormActivation::relu) {
      workspace = torch::empty({static_cast<int64_t>(plan->forward_pd.workspace_desc().get_size())},
                               torch::TensorOptions().dtype(torch::kUInt8));
      args.emplace(DNNL_ARG_WORKSPACE, wrap(plan->forward_pd.workspace_desc(), workspace));
    }
    run(plan->forward, args);
    auto y = normed;
    if (act == NormActivation::swish) {
      y = torch::empty_like(normed, at::MemoryFormat::ChannelsLast);
      run(plan->swish_forward, {{DNNL_ARG_SRC, wrap(plan->data, normed)}, {DNNL_ARG_DST, wrap(plan->data, y)}});
    }
    {  // LibTorch's running statistics: the batch's mean, and its variance made unbiased
      torch::NoGradGuard no_grad;
      const double n = static_cast<double>(B * H * W);
      running_mean.mul_(1 - momentum).add_(mean.to(running_mean.scalar_type()), momentum);
      running_var.mul_(1 - momentum).add_(var.to(running_var.scalar_type()), momentum * n / (n - 1));
    }
    // The fp32 scale and shift as oneDNN read them (its 2.6 backward asks for the shift as well);
    // ReLU's mask (workspace), or swish's input.
    ctx->save_for_backward({x, scale, shift, mean, var, act == NormActivation::relu ? workspace : normed});
    ctx->saved_data["eps"] = eps;
    ctx->saved_data["activation"] = activation;
    ctx->saved_data["weight_type"] = weight.scalar_type();
    return y;
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const auto &x = saved[0], &scale = saved[1], &shift = saved[2], &mean = saved[3], &var = saved[4];
    const int64_t B = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3);
    const auto act = static_cast<NormActivation>(ctx->saved_data["activation"].toInt());
    auto* plan = norm_plan(B, C, H, W, x.scalar_type(), ctx->saved_data["eps"].toDouble(), act);
    auto grad = grads[0].to(x.scalar_type()).contiguous(at::MemoryFormat::ChannelsLast);
    if (act == NormActivation::swish) {  // d/dz of z sigmoid(z), from the saved z
      auto grad_normed = torch::empty_like(x, at::MemoryFormat::ChannelsLast);
      run(plan->swish_backward, {{DNNL_ARG_SRC, wrap(plan->data, saved[5])},
                                 {DNNL_ARG_DIFF_DST, wrap(plan->data, grad)},
                                 {DNNL_ARG_DIFF_SRC, wrap(plan->data, grad_normed)}});
      grad = grad_normed;
    }
    auto grad_x = torch::empty_like(x, at::MemoryFormat::ChannelsLast);
    auto grad_scale = torch::empty({C}, torch::kFloat32), grad_shift = torch::empty({C}, torch::kFloat32);
    std::unordered_map<int, dnnl::memory> args{{DNNL_ARG_SRC, wrap(plan->data, x)},
                                               {DNNL_ARG_DIFF_DST, wrap(plan->data, grad)},
                                               {DNNL_ARG_MEAN, wrap(plan->stats, mean)},
                                               {DNNL_ARG_VARIANCE, wrap(plan->stats, var)},
                                               {DNNL_ARG_SCALE, wrap(plan->stats, scale)},
                                               {DNNL_ARG_SHIFT, wrap(plan->stats, shift)},
                                               {DNNL_ARG_DIFF_SRC, wrap(plan->data, grad_x)},
                                               {DNNL_ARG_DIFF_SCALE, wrap(plan->stats, grad_scale)},
                                               {DNNL_ARG_DIFF_SHIFT, wrap(plan->stats, grad_shift)}};
    if (act == NormActivation::relu)
      args.emplace(DNNL_ARG_WORKSPACE, wrap(plan->forward_pd.workspace_desc(), saved[5]));
    run(plan->backward, args);
    const auto weight_type = ctx->saved_data["weight_type"].toScalarType();
    return {grad_x,
            grad_scale.to(weight_type),
            grad_shift.to(weight_type),
            torch::Tensor(),
            torch::Tensor(),
            torch::Tensor(),
            torch::Tensor(),
            torch::Tensor()};
  }
};

torch::Tensor apply_activation(const torch::Tensor& x, NormActivation activation) {
  return activation == NormActivation::relu ? x.relu_() : x * torch::sigmoid(x);  // x: the batch norm's own output
}

}  // namespace

bool onednn_batch_norm_runs(const torch::Tensor& x, double eps, NormActivation activation) {
  if (!x.defined() || !x.is_cpu() || x.dim() != 4 || !x.is_contiguous(at::MemoryFormat::ChannelsLast)) return false;
  if (x.scalar_type() != torch::kFloat32 && x.scalar_type() != torch::kBFloat16) return false;
  if (x.size(0) * x.size(2) * x.size(3) < 2) return false;  // LibTorch refuses one value per channel
  return norm_plan(x.size(0), x.size(1), x.size(2), x.size(3), x.scalar_type(), eps, activation) != nullptr;
}

torch::Tensor onednn_batch_norm_activation(const torch::Tensor& x, const torch::Tensor& weight,
                                           const torch::Tensor& bias, torch::Tensor running_mean,
                                           torch::Tensor running_var, double momentum, double eps,
                                           NormActivation activation) {
  TORCH_CHECK(x.dim() == 4 && weight.numel() == x.size(1) && bias.numel() == x.size(1),
              "onednn_batch_norm_activation: x {B,C,H,W} and C weights and biases expected, got ", x.sizes(), ", ",
              weight.sizes(), ", ", bias.sizes());
  return BatchNormActivationFunction::apply(x, weight, bias, running_mean, running_var, momentum, eps,
                                            static_cast<int64_t>(activation));
}

torch::Tensor batch_norm_activation(torch::nn::BatchNorm2dImpl& bn, const torch::Tensor& x, NormActivation activation) {
  const auto& o = bn.options;
  if (!bn.is_training() || !o.affine() || !o.track_running_stats() || !o.momentum().has_value() ||
      !onednn_batch_norm_runs(x, o.eps(), activation))
    return apply_activation(bn.forward(x), activation);
  {
    torch::NoGradGuard no_grad;
    bn.num_batches_tracked += 1;  // as BatchNorm2d's own forward counts them
  }
  return onednn_batch_norm_activation(x, bn.weight, bn.bias, bn.running_mean, bn.running_var, *o.momentum(), o.eps(),
                                      activation);
}

}  // namespace flatnet

namespace flatnet {

namespace {

// The three primitives of one training convolution (shape, stride, padding, type, bias), made once
// and shared. Activations are read and written channels-last (NHWC) in place; the weights, fp32
// parameters in their own layout, are reordered into each kernel's blocked layout (and type) per call.
struct TrainConvPlan {
  dnnl::convolution_forward::primitive_desc forward_pd;
  dnnl::convolution_backward_data::primitive_desc data_pd;
  dnnl::convolution_backward_weights::primitive_desc weights_pd;
  dnnl::convolution_forward forward;
  dnnl::convolution_backward_data backward_data;
  dnnl::convolution_backward_weights backward_weights;
  dnnl::memory::desc src, dst, bias;  // NHWC activations, fp32 {O}
  std::array<int64_t, 4> out_shape;
};

using TrainConvKey = std::array<int64_t, 11>;  // B, I, H, W, O, kh, kw, stride, padding, type, bias

// One pass of the convolution (forward, or either gradient): 2 FLOPs per multiply-add.
uint64_t pass_flops(const TrainConvKey& k, const TrainConvPlan& plan) {
  const auto& out = plan.out_shape;
  return static_cast<uint64_t>(2 * out[0] * out[1] * out[2] * out[3] * k[1] * k[5] * k[6]);
}

// oneDNN 2.6's AVX2 weight-gradient kernel reads NHWC activations at a third of its speed on its own
// blocked layout (32->16 channels at 256x256, batch 4: 44-60 ms against 16 ms, plus 2.4 ms of
// reorders); from AVX-512 on the NHWC kernels are as fast. Below AVX-512 the weight gradient gets
// the layout it asks for.
bool weight_gradient_wants_blocked() {
  const auto isa = dnnl::get_effective_cpu_isa();
  return isa < dnnl::cpu_isa::avx512_core;
}

std::unique_ptr<TrainConvPlan> make_train_conv_plan(const TrainConvKey& k) {
  const int64_t B = k[0], I = k[1], H = k[2], W = k[3], O = k[4], KH = k[5], KW = k[6], s = k[7], p = k[8];
  const auto type = static_cast<at::ScalarType>(k[9]) == at::kBFloat16 ? dt::bf16 : dt::f32;
  const bool has_bias = k[10] != 0;
  auto plan = std::make_unique<TrainConvPlan>();
  const int64_t OH = (H + 2 * p - KH) / s + 1, OW = (W + 2 * p - KW) / s + 1;
  plan->out_shape = {B, O, OH, OW};
  plan->src = dnnl::memory::desc({B, I, H, W}, type, tag::nhwc);
  plan->dst = dnnl::memory::desc({B, O, OH, OW}, type, tag::nhwc);
  plan->bias = has_bias ? dnnl::memory::desc({O}, dt::f32, tag::a) : dnnl::memory::desc();
  const dnnl::memory::desc any_weights({O, I, KH, KW}, type, tag::any), f32_weights({O, I, KH, KW}, dt::f32, tag::any);
  const dnnl::memory::dims strides{s, s}, pads{p, p};
  const auto direct = dnnl::algorithm::convolution_direct;
  const auto attr = user_scratchpad();
  plan->forward_pd = dnnl::convolution_forward::primitive_desc(
      dnnl::convolution_forward::desc(dnnl::prop_kind::forward_training, direct, plan->src, any_weights, plan->bias,
                                      plan->dst, strides, pads, pads),
      attr, cpu_engine());
  plan->data_pd = dnnl::convolution_backward_data::primitive_desc(
      dnnl::convolution_backward_data::desc(direct, plan->src, any_weights, plan->dst, strides, pads, pads), attr,
      cpu_engine(), plan->forward_pd);
  const bool blocked = weight_gradient_wants_blocked();
  const dnnl::memory::desc w_src = blocked ? dnnl::memory::desc({B, I, H, W}, type, tag::any) : plan->src;
  const dnnl::memory::desc w_dst = blocked ? dnnl::memory::desc({B, O, OH, OW}, type, tag::any) : plan->dst;
  plan->weights_pd = dnnl::convolution_backward_weights::primitive_desc(
      dnnl::convolution_backward_weights::desc(direct, w_src, f32_weights, plan->bias, w_dst, strides, pads, pads),
      attr, cpu_engine(), plan->forward_pd);
  for (const char* impl :
       {plan->forward_pd.impl_info_str(), plan->data_pd.impl_info_str(), plan->weights_pd.impl_info_str()})
    if (std::string(impl).rfind("ref", 0) == 0) return nullptr;  // a reference loop: LibTorch's path is faster
  plan->forward = dnnl::convolution_forward(plan->forward_pd);
  plan->backward_data = dnnl::convolution_backward_data(plan->data_pd);
  plan->backward_weights = dnnl::convolution_backward_weights(plan->weights_pd);
  return plan;
}

// nullptr where oneDNN has no kernel for it here.
TrainConvPlan* train_conv_plan(const TrainConvKey& key) {
  static std::mutex mutex;
  static std::map<TrainConvKey, std::unique_ptr<TrainConvPlan>> plans;
  return kept_plan(plans, mutex, key, [&] { return make_train_conv_plan(key); });  // nullptr: reference kernels only
}

TrainConvKey train_conv_key(const torch::Tensor& x, const torch::Tensor& weight, bool has_bias, int64_t stride,
                            int64_t padding) {
  return {x.size(0),       x.size(1),      x.size(2), x.size(3), weight.size(0),
          weight.size(2),  weight.size(3), stride,    padding,   static_cast<int64_t>(x.scalar_type()),
          has_bias ? 1 : 0};
}

// A weight tensor as oneDNN reads or writes it: {O,I,kh,kw}, fp32, plain or channels-last.
dnnl::memory user_weights(const torch::Tensor& w) {
  const bool channels_last = w.is_contiguous(at::MemoryFormat::ChannelsLast) && !w.is_contiguous();
  return dnnl::memory({{w.size(0), w.size(1), w.size(2), w.size(3)}, dt::f32, channels_last ? tag::ohwi : tag::oihw},
                      cpu_engine(), w.data_ptr());
}

// `from` as layout `desc`: itself where it already is, else reordered (and converted) into the
// thread's scratch buffer `slot`, valid until that slot's next use.
dnnl::memory reordered(dnnl::memory from, const dnnl::memory::desc& desc, Scratch slot) {
  if (from.get_desc() == desc) return from;
  RECORD_FUNCTION("flatnet::onednn_reorder", c10::ArrayRef<c10::IValue>{});  // in the profiler's tables
  dnnl::memory to(desc, cpu_engine(), scratch(slot, desc.get_size()));
  dnnl::reorder(from, to).execute(cpu_stream(), from, to);
  return to;
}

class TrainConvFunction : public torch::autograd::Function<TrainConvFunction> {
 public:
  // x {B,I,H,W} channels-last fp32 or bf16; weight {O,I,kh,kw} and bias {O} (or {0}: none) fp32.
  static torch::Tensor forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& x,
                               const torch::Tensor& weight, const torch::Tensor& bias_or_empty, int64_t stride,
                               int64_t padding) {
    const auto bias = bias_or_empty.numel() > 0 ? bias_or_empty : torch::Tensor();
    RECORD_FUNCTION("flatnet::onednn_conv2d", std::vector<c10::IValue>({x}));
    const auto key = train_conv_key(x, weight, bias.defined(), stride, padding);
    auto* plan = train_conv_plan(key);
    TORCH_CHECK(plan, "onednn_conv2d: no oneDNN kernel for this convolution");
    const auto w =
        weight.detach().is_contiguous(at::MemoryFormat::ChannelsLast) ? weight.detach() : weight.detach().contiguous();
    auto y = torch::empty({plan->out_shape[0], plan->out_shape[1], plan->out_shape[2], plan->out_shape[3]},
                          x.options().memory_format(at::MemoryFormat::ChannelsLast));  // {B,O,H',W'}
    auto blocked_weights = reordered(user_weights(w), plan->forward_pd.weights_desc(), Scratch::weights);
    std::unordered_map<int, dnnl::memory> args{
        {DNNL_ARG_SRC, wrap(plan->src, x)}, {DNNL_ARG_WEIGHTS, blocked_weights}, {DNNL_ARG_DST, wrap(plan->dst, y)}};
    torch::Tensor b;
    if (bias.defined()) {
      b = bias.detach().to(torch::kFloat32).contiguous();
      args.emplace(DNNL_ARG_BIAS, wrap(plan->bias, b));
    }
    run(plan->forward, args);
    onednn_work += pass_flops(key, *plan);
    ctx->save_for_backward({x, w});
    ctx->saved_data["key"] = std::vector<int64_t>(key.begin(), key.end());
    return y;
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const auto &x = saved[0], &w = saved[1];
    const auto key_list = ctx->saved_data["key"].toIntVector();
    TrainConvKey key;
    std::copy(key_list.begin(), key_list.end(), key.begin());
    auto* plan = train_conv_plan(key);
    const auto grad = grads[0].to(x.scalar_type()).contiguous(at::MemoryFormat::ChannelsLast);  // {B,O,H',W'}
    torch::Tensor grad_x, grad_w, grad_b;
    if (ctx->needs_input_grad(0)) {
      grad_x = input_gradient(*plan, grad, w);
      onednn_work += pass_flops(key, *plan);
    }
    if (ctx->needs_input_grad(1) || ctx->needs_input_grad(2)) {
      std::tie(grad_w, grad_b) = weight_gradients(*plan, x, grad, w, key[10] != 0);
      if (!ctx->needs_input_grad(2)) grad_b = torch::Tensor();
      onednn_work += pass_flops(key, *plan);
    }
    return {grad_x, grad_w, grad_b, torch::Tensor(), torch::Tensor()};
  }

 private:
  // dL/dx: the convolution's transpose applied to the output's gradient.
  static torch::Tensor input_gradient(TrainConvPlan& plan, const torch::Tensor& grad, const torch::Tensor& w) {
    const auto& src = plan.src;
    auto grad_x = torch::empty({src.dims()[0], src.dims()[1], src.dims()[2], src.dims()[3]},
                               grad.options().memory_format(at::MemoryFormat::ChannelsLast));
    auto blocked_weights = reordered(user_weights(w), plan.data_pd.weights_desc(), Scratch::weights);
    run(plan.backward_data, {{DNNL_ARG_DIFF_DST, wrap(plan.dst, grad)},
                             {DNNL_ARG_WEIGHTS, blocked_weights},
                             {DNNL_ARG_DIFF_SRC, wrap(src, grad_x)}});
    return grad_x;
  }

  // dL/dweight (fp32, in the weight's own layout) and dL/dbias (fp32, or undefined without a bias).
  static std::pair<torch::Tensor, torch::Tensor> weight_gradients(TrainConvPlan& plan, const torch::Tensor& x,
                                                                  const torch::Tensor& grad, const torch::Tensor& w,
                                                                  bool has_bias) {
    auto src = reordered(wrap(plan.src, x), plan.weights_pd.src_desc(), Scratch::src);
    auto diff_dst = reordered(wrap(plan.dst, grad), plan.weights_pd.diff_dst_desc(), Scratch::diff_dst);
    auto grad_w = torch::empty_like(w);  // the weight's layout
    auto user_grad = user_weights(grad_w);
    const auto& grad_desc = plan.weights_pd.diff_weights_desc();
    const bool in_place = grad_desc == user_grad.get_desc();
    dnnl::memory blocked_grad =
        in_place ? user_grad : dnnl::memory(grad_desc, cpu_engine(), scratch(Scratch::weights, grad_desc.get_size()));
    std::unordered_map<int, dnnl::memory> args{
        {DNNL_ARG_SRC, src}, {DNNL_ARG_DIFF_DST, diff_dst}, {DNNL_ARG_DIFF_WEIGHTS, blocked_grad}};
    torch::Tensor grad_b;
    if (has_bias) {
      grad_b = torch::empty({w.size(0)}, torch::kFloat32);
      args.emplace(DNNL_ARG_DIFF_BIAS, wrap(plan.bias, grad_b));
    }
    run(plan.backward_weights, args);
    if (!in_place) dnnl::reorder(blocked_grad, user_grad).execute(cpu_stream(), blocked_grad, user_grad);
    cpu_stream().wait();
    return {grad_w, grad_b};
  }
};

// onednn_conv2d once onednn_conv2d_runs has said yes. LibTorch 1.13's custom functions take no
// undefined input: no bias travels as an empty tensor.
torch::Tensor apply_train_conv(const torch::Tensor& x, const torch::Tensor& weight, const torch::Tensor& bias,
                               int64_t stride, int64_t padding) {
  return TrainConvFunction::apply(x, weight, bias.defined() ? bias : torch::empty({0}), stride, padding);
}

}  // namespace

bool onednn_conv2d_runs(const torch::Tensor& x, const torch::Tensor& weight, const torch::Tensor& bias, int64_t stride,
                        int64_t padding) {
  if (!x.defined() || !x.is_cpu() || x.dim() != 4 || !weight.defined() || weight.dim() != 4) return false;
  if (x.suggest_memory_format() != at::MemoryFormat::ChannelsLast || !x.is_contiguous(at::MemoryFormat::ChannelsLast))
    return false;
  if (x.scalar_type() != torch::kFloat32 && x.scalar_type() != torch::kBFloat16) return false;
  if (weight.scalar_type() != torch::kFloat32 || (bias.defined() && bias.scalar_type() != torch::kFloat32))
    return false;
  if (weight.size(1) != x.size(1) || stride < 1 || padding < 0) return false;
  if (x.size(2) + 2 * padding < weight.size(2) || x.size(3) + 2 * padding < weight.size(3)) return false;
  return train_conv_plan(train_conv_key(x, weight, bias.defined(), stride, padding)) != nullptr;
}

torch::Tensor onednn_conv2d(const torch::Tensor& x, const torch::Tensor& weight, const torch::Tensor& bias,
                            int64_t stride, int64_t padding) {
  TORCH_CHECK(onednn_conv2d_runs(x, weight, bias, stride, padding),
              "onednn_conv2d: a channels-last fp32 or bf16 {B,I,H,W} input and an fp32 {O,I,kh,kw} weight expected, "
              "got ",
              x.sizes(), " ", x.scalar_type(), " and ", weight.sizes(), " ", weight.scalar_type());
  return apply_train_conv(x, weight, bias, stride, padding);
}

torch::Tensor convolve(torch::nn::Conv2dImpl& conv, const torch::Tensor& x) {
  const auto& o = conv.options;
  const auto& pad = o.padding();
  const bool plain = o.groups() == 1 && (*o.dilation())[0] == 1 && (*o.dilation())[1] == 1 &&
                     (*o.stride())[0] == (*o.stride())[1] && c10::holds_alternative<torch::ExpandingArray<2>>(pad) &&
                     c10::holds_alternative<torch::enumtype::kZeros>(o.padding_mode());
  if (!plain || !torch::GradMode::is_enabled() || !(x.requires_grad() || conv.weight.requires_grad()))
    return conv.forward(x);
  const auto& p = c10::get<torch::ExpandingArray<2>>(pad);
  if ((*p)[0] != (*p)[1]) return conv.forward(x);
  // fp32 only: under autocast (bf16 on AVX-512) LibTorch's convolutions were as fast (train_cpu_bf16
  // 202-209 ms against 209-219, Zen 5), while in fp32 its backward is slow (train_cpu under the AVX2
  // cap 628-700 -> 551-604 ms; on AVX-512 358-361 -> 332-343).
  if (at::autocast::is_cpu_enabled() || x.scalar_type() != torch::kFloat32) return conv.forward(x);
  const int64_t stride = (*o.stride())[0], padding = (*p)[0];
  if (!onednn_conv2d_runs(x, conv.weight, conv.bias, stride, padding)) return conv.forward(x);
  return apply_train_conv(x, conv.weight, conv.bias, stride, padding);
}

}  // namespace flatnet
