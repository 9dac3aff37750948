// Reading torch.save files as PyTorch users write them (io/torch_file) and importing generators
// from them: committed fixtures (tests/data/torch_save, made by make_fixtures.py) on every
// machine, and files written by /usr/bin/python3 at test time where it has torch.
#include "catch_torch.hpp"
#include <fstream>

#include "core/error.hpp"
#include "helpers.hpp"
#include "tiny_model.hpp"
#include "io/torch_file.hpp"
#include "io/config.hpp"
#include "nn/losses.hpp"
#include "nn/model_file.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

std::filesystem::path fixture(const std::string& name) { return test::data_dir() / "torch_save" / name; }

// make_fixtures.py's ramp: (0.5, 1.5, 2.5, ...) in the given shape.
torch::Tensor ramp(std::vector<int64_t> shape) {
  int64_t n = 1;
  for (auto s : shape) n *= s;
  return (torch::arange(n, torch::kFloat64) + 0.5).reshape(shape).to(torch::kFloat32);
}

torch::Tensor tensor_at(const PyValue& dict, const std::string& key) {
  const auto v = dict.get(key);
  INFO(key);
  REQUIRE(v);
  REQUIRE(v->kind == PyValue::Kind::tensor);
  return v->tensor;
}

void write_bytes(const std::filesystem::path& p, const std::string& bytes) {
  std::ofstream(p, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

std::string read_all(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

}  // namespace

TEST_CASE("torch.save of a state_dict (OrderedDict with _metadata) reads in both containers", "[torchfile]") {
  for (const char* name : {"ordered_dict_zip.pt", "ordered_dict_legacy.pt"}) {
    INFO(name);
    const auto root = read_torch_file(fixture(name));
    REQUIRE(root->is_dict());
    REQUIRE(root->entries.size() == 3);
    CHECK(root->entries[0].first->text == "conv.weight");  // insertion order kept
    CHECK(torch::equal(tensor_at(*root, "conv.weight"), ramp({2, 1, 3, 3})));
    CHECK(torch::equal(tensor_at(*root, "conv.bias"), ramp({2})));
    const auto count = tensor_at(*root, "bn.num_batches_tracked");
    CHECK(count.scalar_type() == torch::kInt64);
    CHECK(count.dim() == 0);
    CHECK(count.item<int64_t>() == 7);
  }
}

TEST_CASE("views of one storage keep their offsets and strides, and other dtypes become float32", "[torchfile]") {
  const auto base = ramp({4, 5});
  for (const char* name : {"views.pt", "views_legacy.pt"}) {
    INFO(name);
    const auto root = read_torch_file(fixture(name));
    CHECK(torch::equal(tensor_at(*root, "base"), base));
    CHECK(torch::equal(tensor_at(*root, "rows"), base.slice(0, 1, 3)));
    CHECK(torch::equal(tensor_at(*root, "t"), base.t()));
    CHECK(torch::equal(tensor_at(*root, "col"), base.select(1, 2)));
  }
  const auto d = read_torch_file(fixture("dtypes.pt"));
  for (const auto& [key, shape] :
       std::vector<std::pair<std::string, std::vector<int64_t>>>{{"f64", {2, 3}}, {"f16", {4}}, {"bf16", {4}}}) {
    INFO(key);
    const auto t = tensor_at(*d, key);
    CHECK(t.scalar_type() == torch::kFloat32);
    CHECK(torch::equal(t, ramp(shape)));  // x.5 values are exact in every one of these types
  }
  CHECK(torch::equal(tensor_at(*d, "i64"), torch::arange(3)));
  CHECK(tensor_at(*d, "scalar").item<float>() == 2.5f);
}

TEST_CASE("nested checkpoints: FlatNet's layout, optimiser state, numbers, lists, None", "[torchfile]") {
  const auto root = read_torch_file(fixture("checkpoint_legacy.pt"));
  CHECK(root->get("epoch")->integer == 12);
  CHECK(root->get("note")->kind == PyValue::Kind::none);
  CHECK(root->get("ok")->boolean);
  const auto gen = root->get("gen_state_dict");
  REQUIRE(gen);
  CHECK(torch::equal(tensor_at(*gen, "PhiL"), ramp({3, 2})));
  const auto groups = root->get("optimizerG_state_dict")->get("param_groups");
  REQUIRE(groups->kind == PyValue::Kind::list);
  CHECK(groups->items[0]->get("lr")->real == Approx(1e-4));
  CHECK(groups->items[0]->get("betas")->items[1]->real == Approx(0.999));
  // tensors_in: every tensor with its dotted path; integer keys (optimiser state) as numbers.
  const auto all = tensors_in(*root);
  std::vector<std::string> names;
  for (const auto& [n, t] : all) names.push_back(n);
  CHECK(std::find(names.begin(), names.end(), "gen_state_dict.bn.weight") != names.end());
  CHECK(std::find(names.begin(), names.end(), "optimizerG_state_dict.state.0.exp_avg") != names.end());
  const auto single = read_torch_file(fixture("single_key.pt"));
  CHECK(torch::equal(tensor_at(*single->get("gen_state_dict"), "w"), ramp({3})));
}

TEST_CASE("bad torch.save files: one clear error naming the file, and no code is ever run", "[torchfile]") {
  test::Scratch s("torchfile_bad");
  CHECK_THROWS_WITH(read_torch_file(s.dir / "missing.pt"), Contains("missing.pt") && Contains("no such file"));
  CHECK_THROWS_WITH(read_torch_file(s.dir), Contains(s.dir.string()) && Contains("is a folder"));
  write_bytes(s.dir / "empty.pt", "");
  CHECK_THROWS_WITH(read_torch_file(s.dir / "empty.pt"), Contains("empty.pt") && Contains("empty"));
  write_bytes(s.dir / "text.pt", "hello");
  CHECK_THROWS_WITH(read_torch_file(s.dir / "text.pt"), Contains("not a torch.save file"));
  // Truncations of a legacy file at every length: an error naming the file, never a crash.
  const auto legacy = read_all(fixture("ordered_dict_legacy.pt"));
  for (size_t n = 1; n < legacy.size(); n += 7) {
    write_bytes(s.dir / "cut.pt", legacy.substr(0, n));
    INFO(n);
    CHECK_THROWS_WITH(read_torch_file(s.dir / "cut.pt"), Contains("cut.pt"));
  }
  // A truncated zip.
  const auto zip = read_all(fixture("ordered_dict_zip.pt"));
  write_bytes(s.dir / "cut.zip.pt", zip.substr(0, zip.size() / 2));
  CHECK_THROWS_WITH(read_torch_file(s.dir / "cut.zip.pt"), Contains("cut.zip.pt"));
  // A pickle that would run a shell command (pickle's classic exploit): refused, with the global's name.
  write_bytes(s.dir / "evil.pt", std::string("\x80\x02"
                                             "cos\nsystem\n"
                                             "X\x05\x00\x00\x00"
                                             "touch"
                                             "\x85R.",
                                             27));
  CHECK_THROWS_WITH(read_torch_file(s.dir / "evil.pt"), Contains("evil.pt") && Contains("os.system"));
  // An unknown opcode, named in hex.
  write_bytes(s.dir / "op.pt", std::string("\x80\x02\xff.", 4));
  CHECK_THROWS_WITH(read_torch_file(s.dir / "op.pt"), Contains("op.pt") && Contains("opcode 0xff"));
}

TEST_CASE("flatnet import finds the generator in every layout people save", "[torchfile][import]") {
  test::Scratch s("torchfile_import");
  // A tiny generator's names, written by this project's exporter; then the same tensors in the
  // layouts of the fixtures, made here from the exported dict with the reader's own output.
  const auto config = Config::load({}, {"model.unet.width=2"});
  const auto camera = test::tiny_camera();
  auto g = test::random_generator(config, camera);
  export_state_dict(s.dir / "sd.pt", g);
  Generator h(generator_options(config, camera, false));
  const auto rep = import_state_dict(s.dir / "sd.pt", h);
  CHECK(rep.unused.empty());
  CHECK_FALSE(rep.data_parallel);
  h->eval();
  const auto Y = torch::randn({1, 4, 20, 24});
  CHECK(torch::equal(h->forward(Y), g->forward(Y)));
  // The fixtures hold other networks' names: the error names the first tensor the model misses.
  for (const char* name :
       {"ordered_dict_zip.pt", "ordered_dict_legacy.pt", "single_key.pt", "data_parallel.pt", "checkpoint_legacy.pt"}) {
    INFO(name);
    CHECK_THROWS_WITH(import_state_dict(fixture(name), h), Contains(name) && Contains("'PhiL'"));
  }
  CHECK_THROWS_WITH(import_state_dict(fixture("views.pt"), h), Contains("views.pt"));
}

TEST_CASE("flatnet import reads what Python writes: OrderedDict, FlatNet checkpoints, DataParallel, legacy",
          "[torchfile][import][python][solo]") {
  if (!test::python_has_torch()) SKIP_TEST("/usr/bin/python3 has no torch");
  test::Scratch s("torchfile_python");
  const auto config = Config::load({}, {"model.unet.width=2"});
  const auto camera = test::tiny_camera();
  auto g = test::random_generator(config, camera);
  export_state_dict(s.dir / "ours.pt", g);
  export_state_dict(s.dir / "ours_flatnet.pt", g, StateDictLayout::flatnet_checkpoint);
  // Python loads our file and saves it back in each layout (the round trip C++ -> Python -> C++).
  const auto script = s.dir / "layouts.py";
  std::ofstream(script) << R"(import collections, sys, torch
sd = torch.load(sys.argv[1])
assert type(sd) is collections.OrderedDict, type(sd)   # exactly what torch.save(model.state_dict()) gives
ck = torch.load(sys.argv[1].replace('ours.pt', 'ours_flatnet.pt'))
assert list(ck.keys()) == ['gen_state_dict'] and list(ck['gen_state_dict'].keys()) == list(sd.keys())
assert all(torch.equal(ck['gen_state_dict'][k], v) for k, v in sd.items())
od = collections.OrderedDict(sd.items())
od._metadata = collections.OrderedDict([('', {'version': 1})])
d = sys.argv[2]
torch.save(od, d + '/ordered.pt')
torch.save(od, d + '/ordered_legacy.pt', _use_new_zipfile_serialization=False)
torch.save({'gen_state_dict': od}, d + '/single.pt')
torch.save({'epoch': 3, 'gen_state_dict': od, 'dis_state_dict': collections.OrderedDict([('w', torch.ones(2))]),
            'optimizerG_state_dict': {'state': {0: {'step': 1, 'exp_avg': torch.zeros(3)}}, 'param_groups': [{'lr': 1e-4, 'params': [0]}]},
            'optimizerD_state_dict': {'state': {}, 'param_groups': []}}, d + '/flatnet_ckpt.pt', _use_new_zipfile_serialization=False)
torch.save(collections.OrderedDict(('module.' + k, v) for k, v in od.items()), d + '/parallel.pt')
torch.save(collections.OrderedDict((k, v.double() if v.is_floating_point() else v) for k, v in od.items()), d + '/double.pt')
torch.save(collections.OrderedDict(list(od.items()) + [('extra.weight', torch.ones(2))]), d + '/extra.pt')
)";
  const auto r =
      test::run_shell("/usr/bin/python3 " + test::q(script) + " " + test::q(s.dir / "ours.pt") + " " + test::q(s.dir));
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto Y = torch::randn({1, 4, 20, 24});
  const auto expected = g->forward(Y);
  for (const char* name :
       {"ordered.pt", "ordered_legacy.pt", "single.pt", "flatnet_ckpt.pt", "parallel.pt", "double.pt", "extra.pt"}) {
    INFO(name);
    Generator h(generator_options(config, camera, false));
    const auto rep = import_state_dict(s.dir / name, h);
    h->eval();
    CHECK(torch::allclose(h->forward(Y), expected, 1e-6, 1e-7));
    CHECK(rep.data_parallel == (std::string(name) == "parallel.pt"));
    CHECK(rep.unused ==
          (std::string(name) == "extra.pt" ? std::vector<std::string>{"extra.weight"} : std::vector<std::string>{}));
  }
}

TEST_CASE("VGG-16 weights load as Python writes them: convert_vgg16.py, torchvision's own file, features.state_dict()",
          "[torchfile][python][vgg][solo]") {
  if (!test::python_has_torch()) SKIP_TEST("/usr/bin/python3 has no torch");
  test::Scratch s("vgg_python");
  // Tensor k (in torchvision's order) holds k + 1e-3 * arange: each loaded value says where it came from.
  const auto script = s.dir / "vgg.py";
  std::ofstream(script) << R"(import collections, sys, torch
d = sys.argv[1]
cfg, names, cin, i = [64, 64, 'M', 128, 128, 'M', 256, 256, 256, 'M', 512, 512, 512], [], 3, 0
for c in cfg:
    if c == 'M':
        i += 1
        continue
    names += [('%d.weight' % i, (c, cin, 3, 3)), ('%d.bias' % i, (c,))]
    cin, i = c, i + 2
def tensor(k, shape):
    n = 1
    for x in shape: n *= x
    return (k + 1e-3 * torch.arange(n, dtype=torch.float64)).reshape(shape).float()
features = collections.OrderedDict((n, tensor(k, sh)) for k, (n, sh) in enumerate(names))
whole = collections.OrderedDict(('features.' + n, t) for n, t in features.items())
whole['classifier.0.weight'] = torch.zeros(4, 3)   # torchvision's file goes on past features[22]
whole._metadata = collections.OrderedDict([('', {'version': 1})])
torch.save(whole, d + '/torchvision.pth')
torch.save(whole, d + '/torchvision_legacy.pth', _use_new_zipfile_serialization=False)
torch.save(dict(whole), d + '/convert.pt')
torch.save(features, d + '/features.pt')
torch.save(collections.OrderedDict(list(features.items())[:-1]), d + '/short.pt')
torch.save([t for t in features.values()], d + '/list.pt')
)";
  const auto r = test::run_shell("/usr/bin/python3 " + test::q(script) + " " + test::q(s.dir));
  INFO(r.output);
  REQUIRE(r.code == 0);
  for (const char* name : {"torchvision.pth", "torchvision_legacy.pth", "convert.pt", "features.pt"}) {
    INFO(name);
    const auto vgg = load_vgg16(s.dir / name);
    const auto params = vgg->parameters();
    REQUIRE(params.size() == 20);
    for (size_t k = 0; k < params.size(); ++k) {
      const auto expected =
          (static_cast<double>(k) + 1e-3 * torch::arange(params[k].numel(), torch::kFloat64)).to(torch::kFloat32);
      CHECK(torch::equal(params[k].flatten(), expected));
    }
  }
  CHECK_THROWS_WITH(load_vgg16(s.dir / "short.pt"), Contains("short.pt") && Contains("features.21.bias"));
  CHECK_THROWS_WITH(load_vgg16(s.dir / "list.pt"), Contains("list.pt") && Contains("expected a dict"));
}
