#pragma once
// The generator spec: what a model is, as typed settings (the `model:` section of a config), and
// the generator it describes for a camera. A model file stores this spec (nn/model_file), not the
// training config read over today's defaults, so that it reads the same with no configs folder and
// whatever later training keys are renamed. Each setting is one row of model_spec_fields(): its
// key, the member it fills, its range and one line of doc; its default is ModelSpec{}'s (a test
// holds them to configs/defaults.yaml). The rows' ranges check every config when it is loaded.
#include <filesystem>
#include <string>
#include <vector>

#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "io/option_table.hpp"
#include "nn/generator.hpp"
#include "nn/losses.hpp"

namespace flatnet {

struct ModelSpec {
  std::string input = "inversion";                // inversion (FlatNet) | tikhonov (the naive model)
  std::string inversion_init = "transpose";       // transpose | pinv | calibfree | flatnet-toeplitz | random | transfer
  bool inversion_shared = true;                   // one W1/W2 pair for the four channels
  std::string inversion_channel = "gb";           // calibration channel for a shared transpose or pinv start
  double inversion_slope = 2.2;                   // calibfree: shadow shift, sensor pixels per scene pixel
  int64_t inversion_seed = 0;                     // calibfree / random: seed of the pseudo-random matrices
  double inversion_lambda = 1.0e-2;               // pinv, transfer: regulariser relative to s_max^2
  std::filesystem::path inversion_toeplitz_file;  // flatnet-toeplitz: phil_toep_slope22.mat
  int64_t preprocessor_width = 0;                 // measurement-domain pre-processor's filters (0: none)
  int64_t preprocessor_depth = 2;                 // its convolutions
  std::string enhancer = "unet";                  // unet | dncnn | rcan | nafnet
  bool level_input = false;                       // the enhancer also reads each plane's light level
  double bn_momentum = 0.99;                      // PyTorch convention (FlatNet: 0.99)
  // The network's picture corrected by its capture through the camera's calibration
  // (recon/data_consistency.hpp, eq. 1), in training and at inference: its strength c (0: none) and
  // the correction's blur (scene pixels).
  double consistency_strength = 0;
  double consistency_blur = 0;
  // The enhancers' own options, whole: the rows bind their sizes (unet.width, dncnn.layers, ...), the
  // defaults are theirs; channels and batch-norm momentum are the generator's to set.
  UNetOptions unet;
  DnCNNOptions dncnn;
  NAFNetOptions nafnet;
  RCANOptions rcan;
};

// The schema's rows for the model section, keys relative to "model." ("unet.width").
const std::vector<OptionField<ModelSpec>>& model_spec_fields();

// A model row's config key: model_key(&ModelSpec::level_input) is "model.level_input", and an
// enhancer's, model_key<&ModelSpec::unet, &UNetOptions::width>(), "model.unet.width".
template <class T>
std::string model_key(T ModelSpec::*member) {
  return key_of(model_spec_fields(), member, "model.");
}
template <auto Outer, auto Inner>
std::string model_key() {
  return nested_key_of<Outer, Inner>(model_spec_fields(), "model.");
}

// The spec a config's `model:` section describes (a value out of range or of the wrong kind: an
// error naming the key).
ModelSpec model_spec(const Config& config);
// The spec as YAML ("model:" with its settings nested, as configs write them); what model files store.
std::string model_spec_yaml(const ModelSpec& spec);
// A spec from YAML text with a `model:` section: the `model_spec` a model file stores, or the
// config that files written before it embedded (converted once, when read: its other sections are
// ignored, and a key it lacks, from before that key existed, takes the spec's default). Errors name
// `where` and the key: a value out of range or of the wrong kind, or, with `strict` (a stored
// spec), a model key this flatnet does not know (a file from a newer flatnet).
ModelSpec parse_model_spec(const std::string& yaml, const std::filesystem::path& where, bool strict);

// The generator a spec describes for a camera. With `initialise`, the first stage gets its
// initial weights (model.inversion.init; the calibration for transpose and naive models);
// without, only the shapes (weights come from a file).
GeneratorOptions generator_options(const ModelSpec& spec, const CameraConfig& camera, bool initialise);
GeneratorOptions generator_options(const Config& config, const CameraConfig& camera, bool initialise);
DiscriminatorOptions discriminator_options(const Config& config);

// Registers model.* and discriminator.* ranges with the config (io/config.hpp), once. Programs call
// train/options.hpp register_option_tables (which calls this); a program without the trainers (the
// fuzz harnesses) calls this.
void register_model_option_tables();
// The discriminator section's rows (keys relative to "discriminator."), and a row's key.
const std::vector<OptionField<DiscriminatorOptions>>& discriminator_fields();
template <class T>
std::string discriminator_key(T DiscriminatorOptions::*member) {
  return key_of(discriminator_fields(), member, "discriminator.");
}

// "trainable inversion W1^T Y W2 (transpose init, one pair for all channels)", "U-Net, width 32":
// what `flatnet info` and the model cards say a model is.
std::string first_stage_text(const ModelSpec& spec);
std::string enhancer_text(const ModelSpec& spec);
// ", pictures corrected by their captures (data consistency c 10, blur 1 px)", or "" for a model without.
std::string consistency_text(const ModelSpec& spec);
// The largest data-consistency blur sigma a `scene`-pixel picture holds (its 3 sigma reach inside the
// scene, which reflection padding needs), and the reason a larger one is refused ("" when it fits):
// one rule for the step at inference, at export, in training and in a model file as it is read.
double largest_consistency_blur(int64_t scene);
std::string consistency_blur_reach_problem(double sigma, int64_t scene);

}  // namespace flatnet
