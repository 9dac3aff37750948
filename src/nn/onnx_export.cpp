#include "nn/onnx_export.hpp"

#include <onnx/checker.h>
#include <onnx/onnx_pb.h>
#include <onnx/shape_inference/implementation.h>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

namespace {

constexpr int kOpset = 13;  // ReduceMean takes `axes` as an attribute up to opset 17; OpenCV 4.6 reads 13
const char* kCameraKey = "flatnet.camera";
const char* kLevelKey = "flatnet.level_input";
const char* kBatchAxis = "batch";  // "1": the graph reads the planes' light level (centring "level")

// Appends nodes and constants to an ONNX graph; every value gets a fresh, readable name.
class GraphBuilder {
 public:
  explicit GraphBuilder(onnx::GraphProto* graph) : g_(graph) {}

  // A float32 constant (an initializer), stored as raw little-endian bytes.
  std::string constant(const std::string& hint, const torch::Tensor& t) {
    const auto c = t.detach().to(torch::kFloat32).contiguous();
    auto* init = g_->add_initializer();
    init->set_name(fresh(hint));
    init->set_data_type(onnx::TensorProto::FLOAT);
    for (auto d : c.sizes()) init->add_dims(d);
    init->set_raw_data(std::string(static_cast<const char*>(c.data_ptr()), c.numel() * sizeof(float)));
    return init->name();
  }
  std::string constant_i64(const std::string& hint, const std::vector<int64_t>& values) {
    auto* init = g_->add_initializer();
    init->set_name(fresh(hint));
    init->set_data_type(onnx::TensorProto::INT64);
    init->add_dims(static_cast<int64_t>(values.size()));
    for (auto v : values) init->add_int64_data(v);
    return init->name();
  }

  // One node with one output (named after `hint`); attributes are added on the returned proto.
  onnx::NodeProto* node(const std::string& op, const std::vector<std::string>& inputs, const std::string& hint) {
    auto* n = g_->add_node();
    n->set_op_type(op);
    n->set_name(fresh(op));
    for (const auto& in : inputs) n->add_input(in);
    n->add_output(fresh(hint));
    return n;
  }
  std::string op(const std::string& type, const std::vector<std::string>& inputs, const std::string& hint) {
    return node(type, inputs, hint)->output(0);
  }
  // x split into its `parts` channels (axis 1, equal sizes).
  std::vector<std::string> split_channels(const std::string& x, int parts, const std::string& hint) {
    auto* n = g_->add_node();
    n->set_op_type("Split");
    n->set_name(fresh("Split"));
    n->add_input(x);
    attr_int(n, "axis", 1);
    std::vector<std::string> outs;
    for (int i = 0; i < parts; ++i) {
      outs.push_back(fresh(hint));
      n->add_output(outs.back());
    }
    return outs;
  }
  std::string concat_channels(const std::vector<std::string>& xs, const std::string& hint) {
    auto* n = node("Concat", xs, hint);
    attr_int(n, "axis", 1);
    return n->output(0);
  }
  std::string transpose_last_two(const std::string& x) {  // {B,C,H,W} -> {B,C,W,H}
    auto* n = node("Transpose", {x}, "t");
    attr_ints(n, "perm", {0, 1, 3, 2});
    return n->output(0);
  }
  // x M for a constant M {K,N}: {B,C,H,K} -> {B,C,H,N}.
  std::string right_matmul(const std::string& x, const torch::Tensor& M, const std::string& hint) {
    return op("MatMul", {x, constant(hint, M)}, hint + "_out");
  }
  // M x for a constant M {N,K}: {B,C,K,W} -> {B,C,N,W}, as (x^T M^T)^T (OpenCV reads a MatMul
  // only with the constant on the right).
  std::string left_matmul(const std::string& x, const torch::Tensor& M, const std::string& hint) {
    return transpose_last_two(right_matmul(transpose_last_two(x), M.t(), hint));
  }

  static void attr_int(onnx::NodeProto* n, const std::string& name, int64_t v) {
    auto* a = n->add_attribute();
    a->set_name(name);
    a->set_type(onnx::AttributeProto::INT);
    a->set_i(v);
  }
  static void attr_float(onnx::NodeProto* n, const std::string& name, double v) {
    auto* a = n->add_attribute();
    a->set_name(name);
    a->set_type(onnx::AttributeProto::FLOAT);
    a->set_f(static_cast<float>(v));
  }
  static void attr_ints(onnx::NodeProto* n, const std::string& name, const std::vector<int64_t>& v) {
    auto* a = n->add_attribute();
    a->set_name(name);
    a->set_type(onnx::AttributeProto::INTS);
    for (auto x : v) a->add_ints(x);
  }

 private:
  std::string fresh(const std::string& hint) { return hint + "_" + std::to_string(counter_++); }
  onnx::GraphProto* g_;
  int64_t counter_ = 0;
};

// A float32 graph input or output {batch, dims...}: the first axis is symbolic ("batch"), so one
// file runs any batch size (ONNX Runtime, TensorRT); OpenCV DNN feeds it one sample at a time.
void declare_batched_tensor(onnx::ValueInfoProto* v, const std::string& name, const std::vector<int64_t>& dims) {
  v->set_name(name);
  auto* t = v->mutable_type()->mutable_tensor_type();
  t->set_elem_type(onnx::TensorProto::FLOAT);
  t->mutable_shape()->add_dim()->set_dim_param(kBatchAxis);
  for (auto d : dims) t->mutable_shape()->add_dim()->set_dim_value(d);
}

int64_t pair_value(const torch::ExpandingArray<2>& a, const char* what) {
  if ((*a)[0] != (*a)[1]) throw Error(std::string("ONNX export: non-square convolution ") + what + " is not supported");
  return (*a)[0];
}

// Emits the graph of one generator. The first stage's output channel order (r, gr, gb, b) is the
// input's reversed, as FlatInversion::forward's flip: here a Split and a reversed Concat.
class GeneratorGraph {
 public:
  GeneratorGraph(GraphBuilder& b, GeneratorImpl& generator) : b_(b), g_(generator) {
    for (const auto& item : g_.named_modules()) modules_[item.key()] = item.value();
  }

  std::string build(const std::string& meas) {
    const auto& o = g_.options();
    std::string planes = meas, level;
    if (o.level_input) {  // split_level: the planes' means off the planes, kept as 4 channels
      auto* mean = b_.node("ReduceMean", {meas}, "level");
      GraphBuilder::attr_ints(mean, "axes", {2, 3});
      GraphBuilder::attr_int(mean, "keepdims", 1);
      level = mean->output(0);                         // {B,4,1,1}
      planes = b_.op("Sub", {meas, level}, "planes");  // {B,4,rows,cols}
    }
    if (o.preprocessor.width > 0) planes = preprocessor(planes);
    auto x = reversed_channels(first_stage(planes));  // {B,4,N,N}
    x = batch_norm(x, "bn");
    if (o.level_input) {  // {B,8,N,N}
      // Expand broadcasts both ways: {B,4,1,1} with {1,4,N,N} gives {B,4,N,N}.
      const auto shape = b_.constant_i64("level_shape", {1, 4, o.scene, o.scene});
      const auto level_map = b_.op("Expand", {reversed_channels(level), shape}, "level_map");
      x = b_.concat_channels({x, level_map}, "with_level");
    }
    switch (o.enhancer) {
      case Enhancer::unet:
        x = unet(x);
        break;
      case Enhancer::dncnn:
        x = sequential(x, "enhancer.body");
        break;
      case Enhancer::rcan:
        throw Error(
            "ONNX export covers the U-Net, DnCNN and NAFNet enhancers; this model's is RCAN (model.enhancer: rcan)");
      case Enhancer::nafnet:
        x = nafnet(x);
        break;
    }
    return x;  // logits
  }

 private:
  template <typename T>
  std::shared_ptr<T> module_as(const std::string& name) {
    auto it = modules_.find(name);
    auto m = it == modules_.end() ? nullptr : std::dynamic_pointer_cast<T>(it->second);
    if (!m) throw Error("ONNX export: the model has no module '" + name + "' of the expected kind");
    return m;
  }

  std::string reversed_channels(const std::string& x) {
    auto parts = b_.split_channels(x, 4, "ch");
    std::reverse(parts.begin(), parts.end());
    return b_.concat_channels(parts, "reversed");
  }

  // MeasurementPreprocessor: Y + g(Y), g its convolutions with leaky ReLUs between them.
  std::string preprocessor(const std::string& planes) {
    const auto& o = g_.options().preprocessor;
    std::string h = planes;
    for (int64_t i = 0; i < o.depth; ++i) {
      const auto name = "preprocessor.convs." + std::to_string(i);
      h = conv(h, *module_as<torch::nn::Conv2dImpl>(name), nullptr, name);
      if (i + 1 == o.depth) break;
      auto* relu = b_.node("LeakyRelu", {h}, "pre_relu");
      GraphBuilder::attr_float(relu, "alpha", o.negative_slope);
      h = relu->output(0);
    }
    return b_.op("Add", {planes, h}, "preprocessed");
  }

  // FlatNet eq. 3 per channel, X_c = leaky_relu(PhiL_c^T Y_c PhiR_c), or the fixed Tikhonov filter
  // of eq. 2.6; output in the input's channel order.
  std::string first_stage(const std::string& planes) {
    const auto& o = g_.options();
    if (o.input == InputStage::tikhonov) return tikhonov(planes);
    auto inv = module_as<FlatInversionImpl>("inversion");
    const auto L = inv->PhiL.detach(), R = inv->PhiR.detach();  // {rows,N,k}, {cols,N,k}
    std::string x;
    if (L.size(2) == 1) {  // one pair for all four channels
      x = b_.left_matmul(b_.right_matmul(planes, R.select(2, 0), "PhiR"), L.select(2, 0).t(), "PhiL");
    } else {
      auto channels = b_.split_channels(planes, 4, "plane");
      for (int c = 0; c < 4; ++c)
        channels[c] = b_.left_matmul(b_.right_matmul(channels[c], R.select(2, c), "PhiR"), L.select(2, c).t(), "PhiL");
      x = b_.concat_channels(channels, "inverted");
    }
    auto* relu = b_.node("LeakyRelu", {x}, "inversion");
    GraphBuilder::attr_float(relu, "alpha", o.inversion.negative_slope);
    return relu->output(0);
  }

  std::string tikhonov(const std::string& planes) {
    // X_c = VL_c [ filter_c o (UL_c^T Y_c UR_c) ] VR_c^T  (eq. 2.6), per channel.
    auto buffers = module_as<TikhonovLayerImpl>("tikhonov")->named_buffers();
    auto channels = b_.split_channels(planes, 4, "plane");
    for (int c = 0; c < 4; ++c) {
      auto x = b_.left_matmul(b_.right_matmul(channels[c], buffers["UR"][c], "UR"), buffers["ULt"][c], "ULt");
      x = b_.op("Mul", {x, b_.constant("filter", buffers["filter"][c].unsqueeze(0).unsqueeze(0))}, "filtered");
      channels[c] = b_.left_matmul(b_.right_matmul(x, buffers["VRt"][c], "VRt"), buffers["VL"][c], "VL");
    }
    return b_.concat_channels(channels, "tikhonov");
  }

  std::string batch_norm(const std::string& x, const std::string& name) {
    auto bn = module_as<torch::nn::BatchNorm2dImpl>(name);
    auto* n = b_.node("BatchNormalization",
                      {x, b_.constant(name + "_scale", bn->weight), b_.constant(name + "_bias", bn->bias),
                       b_.constant(name + "_mean", bn->running_mean), b_.constant(name + "_var", bn->running_var)},
                      name);
    GraphBuilder::attr_float(n, "epsilon", bn->options.eps());
    return n->output(0);
  }

  // A convolution, with the eval-mode batch norm after it (if any) folded in:
  //   W' = s W, b' = s (b - mean) + beta, s = gamma / sqrt(var + eps).
  std::string conv(const std::string& x, const torch::nn::Conv2dImpl& conv, const torch::nn::BatchNorm2dImpl* bn,
                   const std::string& name) {
    auto w = conv.weight.detach().to(torch::kFloat32);
    auto bias = conv.bias.defined() ? conv.bias.detach().to(torch::kFloat32) : torch::zeros({w.size(0)});
    if (bn) {
      const auto s = bn->weight.detach() / torch::sqrt(bn->running_var.detach() + bn->options.eps());
      w = w * s.view({-1, 1, 1, 1});
      bias = s * (bias - bn->running_mean.detach()) + bn->bias.detach();
    }
    const auto& co = conv.options;
    const auto* padding = c10::get_if<torch::ExpandingArray<2>>(&co.padding());
    if (!padding) throw Error("ONNX export: convolution '" + name + "' uses 'same'/'valid' padding");
    const int64_t p = pair_value(*padding, "padding");
    auto* n = b_.node("Conv", {x, b_.constant(name + "_w", w), b_.constant(name + "_b", bias)}, name);
    GraphBuilder::attr_ints(n, "kernel_shape", {w.size(2), w.size(3)});
    GraphBuilder::attr_ints(n, "pads", {p, p, p, p});
    const int64_t s = pair_value(co.stride(), "stride"), d = pair_value(co.dilation(), "dilation");
    GraphBuilder::attr_ints(n, "strides", {s, s});
    GraphBuilder::attr_ints(n, "dilations", {d, d});
    GraphBuilder::attr_int(n, "group", co.groups());
    return n->output(0);
  }

  // A Sequential of Conv2d (each optionally followed by BatchNorm2d) and ReLU, as fold_sequential.
  std::string sequential(std::string x, const std::string& name) {
    auto seq = module_as<torch::nn::SequentialImpl>(name);
    const auto children = seq->children();
    for (size_t i = 0; i < children.size(); ++i) {
      const auto item = name + "." + std::to_string(i);
      if (auto c = std::dynamic_pointer_cast<torch::nn::Conv2dImpl>(children[i])) {
        auto bn =
            i + 1 < children.size() ? std::dynamic_pointer_cast<torch::nn::BatchNorm2dImpl>(children[i + 1]) : nullptr;
        x = conv(x, *c, bn.get(), item);
        if (bn) ++i;
      } else if (std::dynamic_pointer_cast<torch::nn::ReLUImpl>(children[i])) {
        x = b_.op("Relu", {x}, "relu");
      } else {
        throw Error("ONNX export: module '" + item + "' (" + children[i]->name() + ") is not supported");
      }
    }
    return x;
  }

  // FlatNet's U-Net: 4 stride-2 double convolutions down, 4 transposed convolutions up with skips.
  std::string unet(const std::string& input) {
    std::vector<std::string> skips{sequential(input, "enhancer.inc.conv.conv")};  // {B,w,N,N}
    for (int i = 1; i <= 4; ++i)
      skips.push_back(sequential(skips.back(), "enhancer.down" + std::to_string(i) + ".mpconv.0.conv"));
    auto x = skips[4];  // {B,8w,N/16,N/16}
    for (int i = 1; i <= 4; ++i) {
      const auto prefix = "enhancer.up" + std::to_string(i);
      auto up = module_as<torch::nn::ConvTranspose2dImpl>(prefix + ".up");
      auto* n = b_.node("ConvTranspose",
                        {x, b_.constant(prefix + "_up_w", up->weight), b_.constant(prefix + "_up_b", up->bias)},
                        prefix + "_up");
      GraphBuilder::attr_ints(n, "kernel_shape", {2, 2});
      GraphBuilder::attr_ints(n, "strides", {2, 2});
      x = b_.concat_channels({skips[4 - i], n->output(0)}, prefix + "_cat");  // torch::cat({skip, up}), as UpImpl
      x = sequential(x, prefix + ".conv.conv");
    }
    return conv(x, *module_as<torch::nn::Conv2dImpl>("enhancer.outc.conv"), nullptr, "outc");
  }

  // NAFNet's LayerNorm2d over channels: (x - mean_c) / sqrt(var_c + 1e-6) * weight + bias.
  std::string layer_norm(const std::string& x, const std::string& name) {
    auto ln = module_as<LayerNorm2dImpl>(name);
    auto reduce = [&](const std::string& in, const std::string& hint) {
      auto* n = b_.node("ReduceMean", {in}, hint);
      GraphBuilder::attr_ints(n, "axes", {1});
      GraphBuilder::attr_int(n, "keepdims", 1);
      return n->output(0);  // {B,1,H,W}
    };
    // {B,1,H,W} -> {B,C,H,W} by a 1x1 convolution with ones: OpenCV 4.6 broadcasts no computed
    // tensor over the channels (its Mul/Div refuse {B,C,H,W} with {B,1,H,W}).
    const int64_t channels = ln->weight.size(0);
    auto per_channel = [&](const std::string& single) {
      auto* n = b_.node("Conv", {single, b_.constant("ones", torch::ones({channels, 1, 1, 1}))}, "ln_expand");
      GraphBuilder::attr_ints(n, "kernel_shape", {1, 1});
      return n->output(0);
    };
    const auto centred = b_.op("Sub", {x, per_channel(reduce(x, "ln_mean"))}, "ln_centred");
    const auto var = reduce(b_.op("Mul", {centred, centred}, "ln_sq"), "ln_var");
    const auto std =
        b_.op("Sqrt", {b_.op("Add", {var, b_.constant("ln_eps", torch::full({1}, 1e-6))}, "ln_v")}, "ln_std");
    const auto normed = b_.op("Div", {centred, per_channel(std)}, "ln_normed");
    const auto scaled = b_.op("Mul", {normed, b_.constant(name + "_w", ln->weight.view({1, -1, 1, 1}))}, "ln_scaled");
    return b_.op("Add", {scaled, b_.constant(name + "_b", ln->bias.view({1, -1, 1, 1}))}, "ln");
  }

  std::string simple_gate(const std::string& x) {  // {B,2c,H,W} -> {B,c,H,W}
    const auto halves = b_.split_channels(x, 2, "half");
    return b_.op("Mul", {halves[0], halves[1]}, "gate");
  }

  std::string conv_named(const std::string& x, const std::string& name) {
    return conv(x, *module_as<torch::nn::Conv2dImpl>(name), nullptr, name);
  }

  // One NAFBlock (nn/generator.cpp): y = x + beta * conv3(sca(gate(dw(conv1(ln(x)))))),
  // out = y + gamma * conv5(gate(conv4(ln(y)))).
  std::string naf_block(const std::string& in, const std::string& name) {
    auto x = simple_gate(conv_named(conv_named(layer_norm(in, name + ".norm1"), name + ".conv1"), name + ".conv2"));
    auto* pool = b_.node("GlobalAveragePool", {x}, "sca_pool");
    const auto attention = conv_named(pool->output(0), name + ".sca.1");  // {B,c,1,1}
    x = conv_named(b_.op("Mul", {x, attention}, "sca"), name + ".conv3");
    auto params = module_as<torch::nn::Module>(name)->named_parameters(false);
    const auto y = b_.op("Add", {in, b_.op("Mul", {x, b_.constant(name + "_beta", params["beta"])}, "scaled")}, "y");
    x = conv_named(simple_gate(conv_named(layer_norm(y, name + ".norm2"), name + ".conv4")), name + ".conv5");
    return b_.op("Add", {y, b_.op("Mul", {x, b_.constant(name + "_gamma", params["gamma"])}, "scaled")}, "naf");
  }

  std::string naf_blocks(std::string x, const std::string& name) {
    const auto count = module_as<torch::nn::SequentialImpl>(name)->size();
    for (size_t i = 0; i < count; ++i) x = naf_block(x, name + "." + std::to_string(i));
    return x;
  }

  // PyTorch's pixel_shuffle(2): {B,4C,H,W} -> {B,C,2,2,H,W} -> (0,1,4,2,5,3) -> {B,C,2H,2W}. As
  // Reshape and Transpose rather than DepthToSpace (mode CRD), which OpenCV 4.6 does not import.
  std::string pixel_shuffle(const std::string& x, int64_t channels, int64_t size) {
    const auto split = b_.op("Reshape", {x, b_.constant_i64("shuffle_in", {0, channels, 2, 2, size, size})}, "split");
    auto* t = b_.node("Transpose", {split}, "interleaved");
    GraphBuilder::attr_ints(t, "perm", {0, 1, 4, 2, 5, 3});
    return b_.op("Reshape", {t->output(0), b_.constant_i64("shuffle_out", {0, channels, 2 * size, 2 * size})}, "up");
  }

  // NAFNet: intro, 4 levels of blocks + 2x2 stride-2 convolutions down, the middle blocks, then up
  // by a 1x1 convolution and pixel shuffle, skips added.
  std::string nafnet(const std::string& input) {
    auto x = conv_named(input, "enhancer.intro");
    std::vector<std::string> skips;
    for (int i = 0; i < 4; ++i) {
      x = naf_blocks(x, "enhancer.encoders." + std::to_string(i));
      skips.push_back(x);
      x = conv_named(x, "enhancer.downs." + std::to_string(i));
    }
    x = naf_blocks(x, "enhancer.middle_blks");
    for (int i = 0; i < 4; ++i) {
      const auto up = "enhancer.ups." + std::to_string(i) + ".0";
      const int64_t channels = module_as<torch::nn::Conv2dImpl>(up)->options.out_channels() / 4;
      const int64_t size = g_.options().scene >> (4 - i);  // this level's input resolution
      x = b_.op("Add", {pixel_shuffle(conv_named(x, up), channels, size), skips[3 - i]}, "skip");
      x = naf_blocks(x, "enhancer.decoders." + std::to_string(i));
    }
    return conv_named(x, "enhancer.ending");
  }

  GraphBuilder& b_;
  GeneratorImpl& g_;
  std::map<std::string, std::shared_ptr<torch::nn::Module>> modules_;
};

// ONNX's own checks: the model checker, then strict shape inference (a node whose shapes do not
// fit, or an output that disagrees with its declared {1,3,N,N}, throws).
void check_with_onnx(const onnx::ModelProto& model) {
  onnx::checker::check_model(model);
  onnx::ModelProto inferred = model;
  onnx::shape_inference::InferShapes(inferred, onnx::OpSchemaRegistry::Instance(),
                                     onnx::ShapeInferenceOptions(/*check_type=*/true, /*strict=*/1));
}

}  // namespace

OnnxExportReport export_onnx(const std::filesystem::path& path, Generator& generator, const CameraConfig& camera) {
  const auto& o = generator->options();
  check_camera_for_model(o, camera);
  if (o.scene % 16 != 0) throw Error(path, "ONNX export needs a scene size divisible by 16");
  torch::NoGradGuard no_grad;
  onnx::ModelProto model;
  model.set_ir_version(onnx::IR_VERSION);
  model.set_producer_name("flatnet");
  model.set_producer_version(FLATNET_VERSION);
  model.set_doc_string(
      "FlatNet reconstruction: meas {batch,4,rows,cols} (planes b, gb, gr, r as the camera's "
      "preprocessing makes them) -> image {batch,3,N,N} sRGB in [0,1]");
  auto* opset = model.add_opset_import();
  opset->set_domain("");
  opset->set_version(kOpset);
  auto add_meta = [&](const std::string& key, const std::string& value) {
    auto* p = model.add_metadata_props();
    p->set_key(key);
    p->set_value(value);
  };
  add_meta(kCameraKey, camera_geometry_yaml(camera));
  add_meta("flatnet.camera_name", camera.name);
  add_meta(kLevelKey, o.level_input ? "1" : "0");

  auto* graph = model.mutable_graph();
  graph->set_name("flatnet_generator");
  declare_batched_tensor(graph->add_input(), "meas", {4, o.rows, o.cols});
  GraphBuilder builder(graph);
  GeneratorGraph gen(builder, *generator);
  const auto logits = gen.build("meas");
  auto* out = builder.node("Sigmoid", {logits}, "image");
  out->set_output(0, "image");
  declare_batched_tensor(graph->add_output(), "image", {3, o.scene, o.scene});

  try {
    check_with_onnx(model);
  } catch (const std::exception& e) {
    throw Error(path, std::string("the ONNX graph fails ONNX's checker (a flatnet bug; please report): ") + e.what());
  }
  std::string bytes;
  if (!model.SerializeToString(&bytes)) throw Error(path, "the ONNX model could not be serialised (over 2 GB?)");
  write_bytes_atomically(path, bytes);
  return {graph->node_size(), graph->initializer_size(), static_cast<int64_t>(bytes.size())};
}

namespace {

// Bytes per element of an ONNX data type, 0 for types a flatnet graph never holds (strings...).
int64_t onnx_element_bytes(int type) {
  using T = onnx::TensorProto;
  switch (type) {
    case T::FLOAT:
    case T::INT32:
    case T::UINT32:
      return 4;
    case T::DOUBLE:
    case T::INT64:
    case T::UINT64:
      return 8;
    case T::FLOAT16:
    case T::BFLOAT16:
    case T::INT16:
    case T::UINT16:
      return 2;
    case T::INT8:
    case T::UINT8:
    case T::BOOL:
      return 1;
    default:
      return 0;
  }
}

// The values a tensor holds in its typed field (when it has no raw_data), counted.
int64_t onnx_typed_count(const onnx::TensorProto& t) {
  using T = onnx::TensorProto;
  switch (t.data_type()) {
    case T::FLOAT:
      return t.float_data_size();
    case T::DOUBLE:
      return t.double_data_size();
    case T::INT64:
      return t.int64_data_size();
    case T::UINT32:
    case T::UINT64:
      return t.uint64_data_size();
    default:
      return t.int32_data_size();  // INT32, INT16, INT8, UINT16, UINT8, BOOL, FLOAT16, BFLOAT16
  }
}

// A tensor's declared shape against the bytes it holds, before any engine (OpenCV DNN) reads it: a
// file declaring [256,1024,1024] over 4 bytes would make the engine read far past its buffer.
void check_onnx_tensor(const onnx::TensorProto& t, const std::filesystem::path& path) {
  const auto name = "ONNX tensor '" + printable(t.name().substr(0, 80)) + "'";
  require(t.data_location() != onnx::TensorProto::EXTERNAL && t.external_data_size() == 0, path,
          name + " keeps its data in another file; flatnet reads self-contained ONNX files only");
  const int64_t bytes_per = onnx_element_bytes(t.data_type());
  require(bytes_per > 0, path,
          name + " has data type " + std::to_string(t.data_type()) + ", which flatnet's graphs never hold");
  int64_t numel = 1;
  for (const auto d : t.dims()) {
    require(d >= 0 && d <= (int64_t{1} << 31) && numel <= (int64_t{1} << 34) / std::max<int64_t>(d, 1), path,
            name + " declares an impossible shape");
    numel *= d;
  }
  const int64_t held = t.has_raw_data() ? static_cast<int64_t>(t.raw_data().size()) : onnx_typed_count(t) * bytes_per;
  require(held == numel * bytes_per, path,
          name + " declares " + std::to_string(numel) + " values (" + std::to_string(numel * bytes_per) +
              " bytes) and holds " + std::to_string(held) + " bytes");
}

void check_onnx_tensors(const onnx::GraphProto& g, const std::filesystem::path& path) {
  for (const auto& t : g.initializer()) check_onnx_tensor(t, path);
  require(g.sparse_initializer_size() == 0, path, "holds sparse initializers, which flatnet's graphs never hold");
  for (const auto& node : g.node())
    for (const auto& a : node.attribute()) {
      require(
          a.type() != onnx::AttributeProto::GRAPH && a.type() != onnx::AttributeProto::GRAPHS, path,
          "node '" + printable(node.name().substr(0, 80)) + "' holds a subgraph, which flatnet's graphs never hold");
      if (a.has_t()) check_onnx_tensor(a.t(), path);
      for (const auto& t : a.tensors()) check_onnx_tensor(t, path);
    }
}

}  // namespace

OnnxModelInfo read_onnx_info(const std::filesystem::path& path) {
  const auto bytes = read_bytes(path);
  onnx::ModelProto model;
  if (!model.ParseFromArray(bytes.data(), static_cast<int>(bytes.size())))
    throw Error(path, "not an ONNX model (the protobuf does not parse; truncated or another format?)");
  OnnxModelInfo info;
  for (const auto& p : model.metadata_props())
    if (p.key() == kCameraKey)
      info.camera_yaml = p.value();
    else if (p.key() == kLevelKey)
      info.level_input = p.value() == "1";
  const auto& g = model.graph();
  check_onnx_tensors(g, path);
  auto dims = [](const onnx::ValueInfoProto& v) {
    std::vector<int64_t> d;
    for (const auto& dim : v.type().tensor_type().shape().dim()) d.push_back(dim.dim_value());
    return d;
  };
  if (g.input_size() < 1 || g.output_size() != 1)
    throw Error(path, "an ONNX model with one input {batch,4,rows,cols} and one output {batch,3,N,N} expected");
  const auto in = dims(g.input(0)), out = dims(g.output(0));
  if (in.size() != 4 || in[1] != 4 || out.size() != 4 || out[1] != 3 || out[2] != out[3])
    throw Error(path, "an ONNX model with input {batch,4,rows,cols} and output {batch,3,N,N} expected");
  info.rows = in[2];
  info.cols = in[3];
  info.scene = out[2];
  return info;
}

}  // namespace flatnet
