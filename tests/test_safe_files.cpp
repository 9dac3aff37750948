// Files a user hands flatnet may be hostile (issue 25): model files and checkpoints are safetensors
// (data, never code), every size a file claims is checked before anything that size is allocated,
// and configs mean exactly what they say.
#include "catch_torch.hpp"

#include <sys/stat.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "io/mat.hpp"
#include "io/safetensors.hpp"
#include "io/torch_file.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"
#include "tiny_model.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::read_file;
using test::write_file;

namespace {

// A safetensors file from a header given as JSON text and a byte buffer.
std::string handmade(const std::string& header, const std::string& buffer) {
  std::string out(8, '\0');
  for (int i = 0; i < 8; ++i) out[i] = static_cast<char>((static_cast<uint64_t>(header.size()) >> (8 * i)) & 0xff);
  return out + header + buffer;
}

// A model file as flatnet wrote it before format 2: a TorchScript archive from LibTorch's
// OutputArchive (what save_model_file did until 2026-11).
void save_format1_model(const std::filesystem::path& path, Generator& g, const Config& config,
                        const CameraConfig& camera) {
  torch::serialize::OutputArchive a;
  a.write("flatnet_format", c10::IValue(std::string("flatnet-model")));
  a.write("flatnet_version", c10::IValue(int64_t{1}));
  a.write("config", c10::IValue(config.to_yaml()));
  a.write("camera", c10::IValue(camera_geometry_yaml(camera)));
  torch::serialize::OutputArchive sub(a.compilation_unit());
  g->save(sub);
  a.write("generator", sub);
  a.save_to(path.string());
}

Config tiny_config() { return Config::load({}, {"model.unet.width=2"}); }

// A model file of the tiny config with random weights, for tests that need only the file.
void save_tiny_model(const std::filesystem::path& path) {
  const auto config = tiny_config();
  const auto camera = test::tiny_camera();
  auto g = test::random_generator(config, camera);
  save_model_file(path, g, config, camera);
}

bool have_python() { return std::system("python3 -c 'import json, struct, zlib' >/dev/null 2>&1") == 0; }

}  // namespace

TEST_CASE("safetensors: round trip of every dtype, and the file follows the specification", "[safe][model]") {
  test::Scratch s("st_roundtrip");
  std::vector<std::pair<std::string, torch::Tensor>> tensors = {
      {"f32", torch::randn({3, 4})},
      {"f64", torch::randn({2}, torch::kFloat64)},
      {"bf16", torch::randn({5}).to(torch::kBFloat16)},
      {"i64", torch::arange(7, torch::kInt64)},
      {"u8", torch::arange(9, torch::kInt64).to(torch::kUInt8)},
      {"bool", torch::tensor({true, false, true})},
      {"scalar", torch::tensor(2.5)},
      {"empty", torch::zeros({0, 3})},
      {"strided", torch::randn({4, 6}).t()}};
  write_safetensors(s.dir / "a.safetensors", tensors, {{"note", "héllo\nworld"}});
  const auto back = read_safetensors(s.dir / "a.safetensors");
  REQUIRE(back.tensors.size() == tensors.size());
  for (const auto& [name, t] : tensors) {
    INFO(name);
    const auto* b = back.find(name);
    REQUIRE(b);
    CHECK(b->scalar_type() == t.scalar_type());
    CHECK(torch::equal(*b, t.contiguous()));
  }
  CHECK(back.metadata.at("note") == "héllo\nworld");
  CHECK(back.metadata.count(kCrcKey) == 0);  // checked, then removed
  // The data starts 8-byte aligned, as the specification recommends.
  const auto bytes = read_file(s.dir / "a.safetensors");
  uint64_t n = 0;
  std::memcpy(&n, bytes.data(), 8);
  CHECK((8 + n) % 8 == 0);
}

TEST_CASE("model files and checkpoints are read by an independent reader that follows the specification",
          "[safe][model][python][solo]") {
  if (!have_python()) SKIP_TEST("no python3");
  test::Scratch s("st_python");
  const auto config = tiny_config();
  const auto camera = test::tiny_camera();
  auto g = test::random_generator(config, camera);
  save_model_file(s.dir / "m.flatnet", g, config, camera);
  const auto script = test::source_dir() / "scripts" / "safetensors_read.py";
  const auto r = test::run_shell("python3 " + test::q(script) + " " + test::q(s.dir / "m.flatnet") + " --json");
  REQUIRE(r.code == 0);
  const auto j = nlohmann::json::parse(r.output);
  CHECK(j["metadata"]["format"] == "flatnet-model");
  CHECK(j["metadata"]["format_version"] == "2");
  CHECK(j["metadata"]["config"].get<std::string>().find("width: 2") != std::string::npos);
  // Every parameter and buffer, with the same shape and values.
  int64_t seen = 0;
  auto compare = [&](const std::string& name, const torch::Tensor& t) {
    INFO(name);
    const auto& e = j["tensors"]["generator." + name];
    REQUIRE(e.is_object());
    CHECK(e["shape"].get<std::vector<int64_t>>() == t.sizes().vec());
    CHECK(e["sum"].get<double>() == Approx(t.to(torch::kFloat64).sum().item<double>()).margin(1e-9));
    CHECK(e["sum_sq"].get<double>() == Approx(t.to(torch::kFloat64).square().sum().item<double>()).margin(1e-9));
    ++seen;
  };
  for (const auto& p : g->named_parameters()) compare(p.key(), p.value());
  for (const auto& b : g->named_buffers()) compare(b.key(), b.value());
  CHECK(seen == static_cast<int64_t>(j["tensors"].size()));
  // One flipped bit in a weight: the independent reader refuses it too (the CRC-32 in __metadata__).
  auto bytes = read_file(s.dir / "m.flatnet");
  bytes[bytes.size() - 3] ^= 0x10;
  write_file(s.dir / "flipped.flatnet", bytes);
  const auto bad = test::run_shell("python3 " + test::q(script) + " " + test::q(s.dir / "flipped.flatnet"));
  CHECK(bad.code == 1);
  CHECK_THAT(bad.output, Contains("data_crc32"));
  CHECK_THROWS_WITH(load_model_file(s.dir / "flipped.flatnet"), Contains("flipped.flatnet") && Contains("CRC-32"));
}

TEST_CASE("hostile safetensors files: one clear error naming the file, nothing large allocated", "[safe]") {
  test::Scratch s("st_hostile");
  const std::string four(4, '\0');
  auto refused = [&](const std::string& name, const std::string& bytes, const std::string& why) {
    INFO(name);
    write_file(s.dir / name, bytes);
    CHECK_THROWS_WITH(read_safetensors(s.dir / name), Contains(name) && Contains(why));
  };
  const std::string ok = R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}})";
  CHECK_NOTHROW(parse_safetensors(handmade(ok, four), "ok"));
  refused("short.st", "abc", "not a safetensors file");
  std::string huge(8, '\xff');
  refused("huge_header.st", huge + "{}", "over the limit");
  refused("long_header.st", handmade(ok, four).substr(0, 20), "truncated");
  refused("not_json.st", handmade("{\"a\": nope}", ""), "not valid JSON");
  refused("not_object.st", handmade("[1, 2]", ""), "not a safetensors file");
  refused(
      "duplicate.st",
      handmade(
          R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]},"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}})",
          four),
      "twice");
  refused("deep.st", handmade(R"({"a":{"dtype":"F32","shape":[[[[1]]]],"data_offsets":[0,4]}})", four), "nests");
  refused("dtype.st", handmade(R"({"a":{"dtype":"F8_E4M3","shape":[1],"data_offsets":[0,1]}})", "x"),
          "dtype 'F8_E4M3'");
  refused("overflow.st",
          handmade(R"({"a":{"dtype":"F32","shape":[4294967296,4294967296],"data_offsets":[0,4]}})", four), "overflows");
  refused("mismatch.st", handmade(R"({"a":{"dtype":"F32","shape":[1000000000],"data_offsets":[0,4]}})", four),
          "need 4000000000");
  refused("past_end.st", handmade(R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}})", four), "truncated");
  refused("hole.st", handmade(R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[4,8]}})", std::string(8, '\0')),
          "holes");
  refused(
      "overlap.st",
      handmade(
          R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]},"b":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}})",
          four),
      "holes or overlapping");
  refused("trailing.st", handmade(ok, four + "junk"), "belong to none");
  refused("bool.st", handmade(R"({"a":{"dtype":"BOOL","shape":[1],"data_offsets":[0,1]}})", "\x07"), "0 and 1");
  refused("meta.st", handmade(R"({"__metadata__":{"k":1}})", ""), "not a string");
  refused("negative.st", handmade(R"({"a":{"dtype":"F32","shape":[-1],"data_offsets":[0,4]}})", four), "non-negative");
  // A model file whose tensors are fine but whose CRC-32 does not match.
  refused("crc.st",
          handmade(R"({"__metadata__":{"data_crc32":"00000000"},"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}})",
                   std::string("\1\2\3\4", 4)),
          "CRC-32");
}

TEST_CASE("a file's kind comes from its header alone, and the header gets every check", "[safe][model]") {
  test::Scratch s("st_kind");
  save_tiny_model(s.dir / "m.flatnet");
  // The metadata read from the header is the metadata the whole-file reader returns.
  CHECK(read_safetensors_metadata(s.dir / "m.flatnet") == read_safetensors(s.dir / "m.flatnet").metadata);
  CHECK_FALSE(is_checkpoint_file(s.dir / "m.flatnet"));
  // A checkpoint's header over a buffer that is not read: a wrong CRC-32 and a tensor past the end
  // still tell the kind (loading it is refused, naming the file).
  const std::string checkpoint_header = R"({"__metadata__":{"format":"flatnet-checkpoint","data_crc32":"00000000"},)"
                                        R"("a":{"dtype":"F32","shape":[1000],"data_offsets":[0,4000]}})";
  write_file(s.dir / "c.flatnet", handmade(checkpoint_header, "1234"));
  CHECK(is_checkpoint_file(s.dir / "c.flatnet"));
  CHECK(read_safetensors_metadata(s.dir / "c.flatnet").at("format") == "flatnet-checkpoint");
  CHECK(read_safetensors_metadata(s.dir / "c.flatnet").count(kCrcKey) == 0);
  CHECK_THROWS_WITH(read_safetensors(s.dir / "c.flatnet"), Contains("c.flatnet") && Contains("truncated"));
  // Written the way Python writes one (json.dumps, struct.pack, no padding, no metadata at all).
  if (have_python()) {
    const auto r = test::run_shell(
        "python3 -c \"import json, struct, sys; h = json.dumps({'w': {'dtype': 'F32', 'shape': [2], "
        "'data_offsets': [0, 8]}}).encode(); open(sys.argv[1], 'wb').write(struct.pack('<Q', len(h)) + h + "
        "struct.pack('<2f', 1.5, -2))\" " +
        test::q(s.dir / "py.safetensors"));
    REQUIRE(r.code == 0);
    CHECK(read_safetensors_metadata(s.dir / "py.safetensors").empty());
    CHECK_FALSE(is_checkpoint_file(s.dir / "py.safetensors"));
  }
  // The header's own faults, each naming the file.
  auto refused = [&](const std::string& name, const std::string& bytes, const std::string& why) {
    INFO(name);
    write_file(s.dir / name, bytes);
    CHECK_THROWS_WITH(read_safetensors_metadata(s.dir / name), Contains(name) && Contains(why));
    CHECK_THROWS_WITH(is_checkpoint_file(s.dir / name), Contains(name) && Contains(why));
  };
  refused("huge_header.st", std::string(8, '\xff') + "{}", "over the limit");
  refused("long_header.st", handmade(checkpoint_header, "").substr(0, 40), "truncated");
  refused("not_json.st", handmade("{\"a\": nope}", ""), "not valid JSON");
  refused("meta.st", handmade(R"({"__metadata__":{"format":1}})", ""), "not a string");
  CHECK_THROWS_WITH(is_checkpoint_file(s.dir / "absent.flatnet"),
                    Contains("absent.flatnet") && Contains("no such file"));
  CHECK_THROWS_WITH(is_checkpoint_file(s.dir), Contains("is a folder"));
  CHECK_THROWS_WITH(read_safetensors_metadata(s.dir / "short"),
                    Contains("short") && Contains("no such file"));  // before it exists
  write_file(s.dir / "short", "abc");
  CHECK_THROWS_WITH(read_safetensors_metadata(s.dir / "short"), Contains("short") && Contains("not a safetensors"));
  CHECK_FALSE(is_checkpoint_file(s.dir / "short"));  // neither safetensors nor an archive: not a checkpoint
}

TEST_CASE("format-1 model files (TorchScript archives) are read as data, with the same outputs", "[safe][model]") {
  test::Scratch s("format1");
  const auto config = tiny_config();
  const auto camera = test::tiny_camera();
  auto g = test::random_generator(config, camera);
  const auto Y = torch::randn({1, 4, 20, 24});
  const auto expected = g->forward(Y);
  save_format1_model(s.dir / "old.flatnet", g, config, camera);
  CHECK(model_file_version(s.dir / "old.flatnet") == 1);
  auto m = load_model_file(s.dir / "old.flatnet");
  CHECK(m.format_version == 1);
  CHECK(torch::equal(m.generator->forward(Y), expected));
  // `flatnet export --model OLD --out NEW` rewrites it as format 2, the same weights.
  const auto r = test::run_flatnet("export --model " + test::q(s.dir / "old.flatnet") + " --out " +
                                   test::q(s.dir / "new.flatnet"));
  REQUIRE(r.code == 0);
  CHECK(model_file_version(s.dir / "new.flatnet") == 2);
  CHECK(torch::equal(load_model_file(s.dir / "new.flatnet").generator->forward(Y), expected));
}

TEST_CASE("a TorchScript model with a __setstate__ is never run by any command that loads models",
          "[safe][model][python][solo]") {
  if (!test::python_has_torch()) SKIP_TEST("/usr/bin/python3 has no torch");
  test::Scratch s("setstate");
  // The module's __setstate__ prints a marker when LibTorch's (or Python's) loader restores it, as
  // the issue's exploit wrote a file.
  write_file(s.dir / "make.py", R"(import sys, torch
from typing import Tuple
class Evil(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.flatnet_format = "flatnet-model"
        self.w = torch.zeros(2)
    @torch.jit.export
    def __getstate__(self):
        return (self.w, self.flatnet_format, self.training)
    @torch.jit.export
    def __setstate__(self, state: Tuple[torch.Tensor, str, bool]):
        self.w = state[0]
        self.flatnet_format = state[1]
        self.training = state[2]
        print("PWNED-SETSTATE")
    def forward(self, x):
        return x
torch.jit.save(torch.jit.script(Evil()), sys.argv[1])
)");
  const auto made =
      test::run_shell("/usr/bin/python3 " + test::q(s.dir / "make.py") + " " + test::q(s.dir / "evil.flatnet"));
  if (made.code != 0) SKIP_TEST("this torch cannot script the probe: " + made.output.substr(0, 200));
  // The probe is real: Python's own loader runs it.
  const auto python = test::run_shell("/usr/bin/python3 -c \"import torch; torch.jit.load('" +
                                      (s.dir / "evil.flatnet").string() + "')\"");
  CHECK_THAT(python.output, Contains("PWNED-SETSTATE"));
  std::filesystem::create_directories(s.dir / "in");
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_raw.png", s.dir / "in" / "a.png");
  for (const std::string& cmd :
       {"infer --model " + test::q(s.dir / "evil.flatnet") + " --input " + test::q(s.dir / "in") + " --out " +
            test::q(s.dir / "o"),
        "export --model " + test::q(s.dir / "evil.flatnet") + " --out " + test::q(s.dir / "x.flatnet")}) {
    INFO(cmd);
    const auto r = test::run_flatnet(cmd);
    CHECK(r.code != 0);
    CHECK_THAT(r.output, Contains("evil.flatnet"));
    CHECK_THAT(r.output, !Contains("PWNED"));
  }
  CHECK_THROWS_WITH(load_model_file(s.dir / "evil.flatnet"), Contains("evil.flatnet"));
  auto g = test::random_generator(tiny_config(), test::tiny_camera());  // train --init-from
  CHECK_THROWS_WITH(init_generator_from(s.dir / "evil.flatnet", g), Contains("evil.flatnet"));
}

TEST_CASE("a model file's spec is checked against its weights before the network is built", "[safe][model]") {
  test::Scratch s("sizes");
  save_tiny_model(s.dir / "m.flatnet");
  // `legacy`: as files from before the typed spec, whose embedded training config describes the model.
  auto tamper = [&](const std::string& name, const std::string& key, const std::string& from, const std::string& to,
                    bool legacy = false) {
    auto st = read_safetensors(s.dir / "m.flatnet");
    if (legacy) st.metadata.erase("model_spec");
    auto& text = st.metadata.at(key);
    const auto at = text.find(from);
    REQUIRE(at != std::string::npos);
    text.replace(at, from.size(), to);
    write_safetensors(s.dir / name, st.tensors, st.metadata);
  };
  tamper("wide.flatnet", "model_spec", "width: 2\n", "width: 4096\n");
  CHECK_THROWS_WITH(load_model_file(s.dir / "wide.flatnet"),
                    Contains("wide.flatnet") && Contains("model.unet.width = 4096 disagrees with the weights"));
  tamper("old-wide.flatnet", "config", "width: 2\n", "width: 4096\n", /*legacy=*/true);
  CHECK_THROWS_WITH(load_model_file(s.dir / "old-wide.flatnet"),
                    Contains("old-wide.flatnet") && Contains("model.unet.width = 4096 disagrees with the weights"));
  // The training config is a record beside a stored spec: a width written there is not read.
  tamper("recipe.flatnet", "config", "width: 2\n", "width: 4096\n");
  CHECK(load_model_file(s.dir / "recipe.flatnet").spec.unet.width == 2);
  tamper("future.flatnet", "model_spec", "unet:\n", "warp: 9\n  unet:\n");
  CHECK_THROWS_WITH(load_model_file(s.dir / "future.flatnet"),
                    Contains("future.flatnet") && Contains("model.warp") && Contains("newer"));
  tamper("scene.flatnet", "camera", "scene_size: 16", "scene_size: 4096");
  CHECK_THROWS_WITH(load_model_file(s.dir / "scene.flatnet"),
                    Contains("scene.flatnet") && Contains("scene_size = 4096 disagrees"));
  tamper("bigscene.flatnet", "camera", "scene_size: 16", "scene_size: 4194304");
  CHECK_THROWS_WITH(load_model_file(s.dir / "bigscene.flatnet"),
                    Contains("bigscene.flatnet") && Contains("scene_size is 1 to 4096"));
  tamper("hex.flatnet", "model_spec", "width: 2\n", "width: 0x2\n");
  CHECK_THROWS_WITH(load_model_file(s.dir / "hex.flatnet"), Contains("hex.flatnet") && Contains("model.unet.width"));
  // A weight its spec has no place for (a spec edited to `input: tikhonov` over a trained inversion's
  // weights, say) is named, not dropped.
  auto st = read_safetensors(s.dir / "m.flatnet");
  const auto some = st.tensors.begin()->first;
  REQUIRE(some.rfind("generator.", 0) == 0);
  st.tensors.emplace_back("generator.inversion.extra", torch::zeros({3}));
  write_safetensors(s.dir / "extra.flatnet", st.tensors, st.metadata);
  CHECK_THROWS_WITH(load_model_file(s.dir / "extra.flatnet"),
                    Contains("extra.flatnet") && Contains("inversion.extra") && Contains("no place"));
}

TEST_CASE("hostile pickles: cycles, deep nesting, huge lengths and amplifying views are refused", "[safe][torchfile]") {
  test::Scratch s("pickles");
  auto refused = [&](const std::string& name, const std::string& pickle, const std::string& why) {
    INFO(name);
    write_file(s.dir / name, pickle);
    CHECK_THROWS_WITH(read_torch_file(s.dir / name), Contains(name) && Contains(why));
  };
  // [l] with l.append(l): EMPTY_LIST, BINPUT 0, BINGET 0, APPEND, STOP.
  refused("self.pt",
          std::string("\x80\x02]q\x00h\x00"
                      "a.",
                      9),
          "contains itself");
  // a = []; b = [a]; a.append(b): a changes after it was placed in b.
  refused("cycle.pt",
          std::string{'\x80', '\x02', ']', 'q', '\0', ']', 'q', '\1', 'h', '\0', 'a', '0', 'h', '\1', 'a', '.'},
          "after placing it");
  // 200000 nested lists.
  refused("deep.pt", std::string("\x80\x02", 2) + std::string(200000, ']') + std::string(199999, 'a') + ".",
          "deeper than 64");
  // A string that claims 2^64 - 5 bytes.
  refused("long.pt", std::string("\x80\x02\x8d\xfb\xff\xff\xff\xff\xff\xff\xff", 11) + "abc.", "truncated");
  // A DAG that doubles at every level: 40 levels of [x, x].
  std::string dag("\x80\x02]q\x00", 5);
  for (int i = 0; i < 40; ++i) dag += std::string("(h\x00h\x00lq\x00", 8);
  dag += ".";
  refused("dag.pt", dag, "expands to more than");
}

TEST_CASE("a view that claims more elements than its storage holds is refused before the copy",
          "[safe][torchfile][python][solo]") {
  if (!test::python_has_torch()) SKIP_TEST("/usr/bin/python3 has no torch");
  test::Scratch s("amplify");
  const auto r = test::run_shell(
      "/usr/bin/python3 -c \"import torch; torch.save({'w': torch.zeros(1).expand(32768, "
      "16384)}, '" +
      (s.dir / "amp.pt").string() + "')\"");
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::file_size(s.dir / "amp.pt") < 4096);
  CHECK_THROWS_WITH(read_torch_file(s.dir / "amp.pt"), Contains("amp.pt") && Contains("overlapping strides"));
}

TEST_CASE("configs mean what they say: no stray paths, no hex, no duplicate keys or second documents",
          "[safe][config]") {
  test::Scratch s("strict_config");
  // A file called "1" in the working folder does not turn train.batch=1 into a path.
  const auto cwd = std::filesystem::current_path();
  std::filesystem::current_path(s.dir);
  write_file(s.dir / "1", "stray");
  const auto c = Config::load({}, {"train.batch=1"});
  const auto text = c.to_yaml();
  std::filesystem::current_path(cwd);
  CHECK(Config::from_text(text, "saved").integer("train.batch") == 1);
  CHECK_THROWS_WITH(Config::load({}, {"train.batch=0x10"}), Contains("train.batch") && Contains("decimal"));
  CHECK_THROWS_WITH(Config::load({}, {"train.lr=inf"}), Contains("train.lr"));
  write_file(s.dir / "dup.yaml", "train:\n  lr: 1.0e-4\n  lr: 2.0e-4\n");
  CHECK_THROWS_WITH(Config::load(s.dir / "dup.yaml"), Contains("dup.yaml") && Contains("'lr' is given twice"));
  write_file(s.dir / "two.yaml", "train:\n  lr: 1.0e-4\n---\ntrain:\n  lr: 2.0e-4\n");
  CHECK_THROWS_WITH(Config::load(s.dir / "two.yaml"), Contains("two.yaml") && Contains("more than one YAML document"));
  write_file(s.dir / "big.yaml", "train:\n  " + std::string(5 << 20, 'x') + ": 1\n");  // over 4 MiB
  CHECK_THROWS_WITH(Config::load(s.dir / "big.yaml"), Contains("big.yaml") && Contains("over the limit"));
  // Cameras: NaN rotation, infinite or absurd regularisation, absurd scene sizes.
  const std::string camera = "raw_height: 40\nraw_width: 48\ncrop: [0, 0, 20, 24]\nscene_size: 16\n";
  for (const auto& [extra, why] :
       std::vector<std::pair<std::string, std::string>>{{"rotation: .nan\n", "rotation"},
                                                        {"tikhonov_lambda: .inf\n", "tikhonov_lambda is (0, 1e4]"},
                                                        {"tikhonov_lambda: 1e300\n", "tikhonov_lambda is (0, 1e4]"}}) {
    INFO(extra);
    write_file(s.dir / "cam.yaml", camera + extra);
    CHECK_THROWS_WITH(load_camera_config(s.dir / "cam.yaml"), Contains("cam.yaml") && Contains(why));
  }
}

TEST_CASE("fifos and devices are refused at once, never waited on", "[safe]") {
  test::Scratch s("fifo");
  const auto fifo = s.dir / "pipe";
  REQUIRE(::mkfifo(fifo.c_str(), 0600) == 0);
  // A reader that waited on the fifo (no writer ever opens it) would block for ever: the refusal is
  // the verdict, and a wait would be a hang that CTest ends, not a clock this test reads.
  CHECK_THROWS_WITH(read_file_text(fifo), Contains("pipe") && Contains("not a regular file"));
  CHECK_THROWS_WITH(load_model_file(fifo), Contains("pipe") && Contains("not a regular file"));
  CHECK_THROWS_WITH(Config::load(fifo), Contains("pipe"));
  CHECK_THROWS_WITH(load_camera_config(fifo), Contains("pipe") && Contains("not a regular file"));
  CHECK_THROWS_WITH(read_torch_file(fifo), Contains("pipe") && Contains("not a regular file"));
  CHECK_THROWS_WITH(read_file_text("/dev/zero"), Contains("/dev/zero") && Contains("not a regular file"));
  CHECK_THROWS_WITH(read_file_head(fifo, 9), Contains("pipe") && Contains("not a regular file"));
  CHECK_THROWS_WITH(is_checkpoint_file(fifo), Contains("pipe") && Contains("not a regular file"));
  write_file(s.dir / "big.bin", std::string(100, 'x'));
  CHECK_THROWS_WITH(read_file_text(s.dir / "big.bin", 10), Contains("big.bin") && Contains("over the limit"));
  // A head is the first bytes, or the whole file when it is shorter.
  CHECK(read_file_head(s.dir / "big.bin", 10) == std::string(10, 'x'));
  CHECK(read_file_head(s.dir / "big.bin", 1000) == std::string(100, 'x'));
}

namespace {

// A MATLAB v5 file with one uncompressed double variable whose header says rows x cols and whose
// data holds `values` (what MATLAB writes when they agree).
std::string mat5(const std::string& name, int32_t rows, int32_t cols, const std::vector<double>& values) {
  auto u32 = [](uint32_t v) { return std::string(reinterpret_cast<const char*>(&v), 4); };
  auto element = [&](uint32_t type, const std::string& data) {
    return u32(type) + u32(static_cast<uint32_t>(data.size())) + data + std::string((8 - data.size() % 8) % 8, '\0');
  };
  std::string header = "MATLAB 5.0 MAT-file, written by a test";
  header.resize(116, ' ');
  header += std::string(8, '\0') + std::string("\x00\x01IM", 4);
  const std::string body = element(6, u32(6) + u32(0)) +
                           element(5, std::string(reinterpret_cast<const char*>(&rows), 4) +
                                          std::string(reinterpret_cast<const char*>(&cols), 4)) +
                           element(1, name) +
                           element(9, std::string(reinterpret_cast<const char*>(values.data()), 8 * values.size()));
  return header + u32(14) + u32(static_cast<uint32_t>(body.size())) + body;
}

}  // namespace

TEST_CASE(".mat files: what a variable claims is checked against its data before matio allocates", "[safe][mat]") {
  test::Scratch s("mat_sizes");
  write_file(s.dir / "ok.mat", mat5("A", 2, 2, {1, 2, 3, 4}));
  const auto a = MatReader(s.dir / "ok.mat").read("A");
  CHECK(a.sizes() == c10::IntArrayRef{2, 2});
  CHECK(a[1][0].item<double>() == 2);  // column-major
  write_file(s.dir / "short.mat", mat5("P1b", 500, 256, {1, 2, 3, 4}));
  CHECK_THROWS_WITH(MatReader(s.dir / "short.mat"),
                    Contains("short.mat") && Contains("'P1b'") && Contains("128000 values, its data holds 4"));
  write_file(s.dir / "huge.mat", mat5("P1b", 20000, 20000, {1, 2, 3, 4}));
  CHECK(std::filesystem::file_size(s.dir / "huge.mat") < 300);
  CHECK_THROWS_WITH(MatReader(s.dir / "huge.mat"), Contains("huge.mat") && Contains("400000000 values"));
  auto cut = mat5("A", 2, 2, {1, 2, 3, 4});
  write_file(s.dir / "cut.mat", cut.substr(0, cut.size() - 9));
  CHECK_THROWS_WITH(MatReader(s.dir / "cut.mat"), Contains("cut.mat") && Contains("truncated"));
  // Files matio writes (compressed v5) and the shipped camera files pass.
  write_mat(s.dir / "written.mat", {{"B", torch::randn({30, 7}, torch::kFloat64)}});
  CHECK(MatReader(s.dir / "written.mat").read("B").size(1) == 7);
  for (const auto& f : {test::rig_path(), test::calib_path()}) CHECK_NOTHROW(MatReader(f).names());
}

TEST_CASE(".mat files as MATLAB, scipy and FlatNet's release wrote them pass the size check", "[safe][mat][shared]") {
  std::vector<std::filesystem::path> files;
  for (const auto& root : {test::source_dir() / "models", test::shared_dir() / "data"})
    if (std::filesystem::exists(root))
      for (const auto& e : std::filesystem::recursive_directory_iterator(root))
        if (e.path().extension() == ".mat") files.push_back(e.path());
  REQUIRE(files.size() >= 8);  // the shipped camera, codes, masks and NIQE model at least
  for (const auto& f : files) {
    INFO(f);
    CHECK_NOTHROW(MatReader(f).names());
  }
}

TEST_CASE("averaged models (export --average-of): the mean of the weights, of one model and camera only",
          "[model][average]") {
  test::Scratch s("average");
  const auto config = tiny_config();
  const auto camera = test::tiny_camera();
  std::vector<Generator> generators;
  std::vector<std::filesystem::path> paths;
  for (int i = 0; i < 3; ++i) {
    generators.push_back(test::random_generator(config, camera));
    paths.push_back(s.dir / ("m" + std::to_string(i) + ".flatnet"));
    Provenance record;
    record.trained_steps = std::to_string(1000 * (i + 1));
    record.scores = R"({"heldout": {"images": 2, "psnr": 20.0}})";
    save_model_file(paths.back(), generators.back(), config, camera, record);
  }
  const auto mean = average_models(paths);
  // Every parameter and floating-point buffer is the mean of the three; integer buffers
  // (num_batches_tracked) are the last file's.
  auto check_mean = [&](const std::string& name, const torch::Tensor& got, auto tensors_of) {
    INFO(name);
    if (!got.is_floating_point()) {
      CHECK(torch::equal(got, tensors_of(generators[2])[name]));
      return;
    }
    const auto expect =
        (tensors_of(generators[0])[name].to(torch::kFloat64) + tensors_of(generators[1])[name].to(torch::kFloat64) +
         tensors_of(generators[2])[name].to(torch::kFloat64)) /
        3;
    CHECK(torch::allclose(got.to(torch::kFloat64), expect, 1e-6, 1e-7));
    CHECK_FALSE(torch::equal(got, tensors_of(generators[2])[name]));  // not simply one of them
  };
  for (const auto& p : mean.generator->named_parameters())
    check_mean(p.key(), p.value(), [](Generator& g) { return g->named_parameters(); });
  int buffers = 0;
  for (const auto& b : mean.generator->named_buffers()) {
    ++buffers;
    check_mean(b.key(), b.value(), [](Generator& g) { return g->named_buffers(); });
  }
  CHECK(buffers > 0);  // batch-norm running statistics are averaged too
  // The last file's record, every file named as the source, and no held-out scores (they were
  // measured on one file's weights, not on the mean).
  CHECK(mean.provenance.trained_steps == "3000");
  CHECK(mean.provenance.scores.empty());
  CHECK_THAT(mean.provenance.source, Contains("mean of 3 models") && Contains("m0.flatnet") && Contains("m2.flatnet"));

  // The mean of a model with itself is that model, and the mean written and read again is the mean.
  const auto same = average_models({paths[0], paths[0]});
  for (const auto& p : same.generator->named_parameters())
    CHECK(torch::allclose(p.value(), generators[0]->named_parameters()[p.key()], 1e-6, 1e-8));
  auto written = mean;
  save_model_file(s.dir / "mean.flatnet", written.generator, model_identity(mean));
  const auto read_back = load_model_file(s.dir / "mean.flatnet");
  for (const auto& p : read_back.generator->named_parameters())
    CHECK(torch::equal(p.value(), mean.generator->named_parameters()[p.key()]));
  CHECK(read_back.provenance.source == mean.provenance.source);

  // Refused, naming the file: one file alone, another architecture, another camera, not a model.
  CHECK_THROWS_WITH(average_models({paths[0]}), Contains("at least two"));
  const auto wide_config = Config::load({}, {"model.unet.width=4"});
  auto wide = test::random_generator(wide_config, camera);
  save_model_file(s.dir / "wide.flatnet", wide, wide_config, camera);
  CHECK_THROWS_WITH(average_models({paths[0], s.dir / "wide.flatnet"}),
                    Contains("wide.flatnet") && Contains("different model"));
  auto other_camera = camera;
  other_camera.name = "bench-2";
  save_model_file(s.dir / "other.flatnet", generators[1], config, other_camera);
  CHECK_THROWS_WITH(average_models({paths[0], paths[1], s.dir / "other.flatnet"}),
                    Contains("other.flatnet") && Contains("another camera") && Contains("bench-2"));
  write_file(s.dir / "junk.flatnet", "not a model");
  CHECK_THROWS_WITH(average_models({paths[0], s.dir / "junk.flatnet"}), Contains("junk.flatnet"));
}

TEST_CASE("reinit inversion (train --reinit) keeps the enhancer and gives the first stage this camera's initialisation",
          "[model][adapt]") {
  test::Scratch s("reinit");
  auto config = Config::load({}, {"model.unet.width=2", "model.inversion.init=random", "model.inversion.seed=1"});
  const auto camera = test::tiny_camera();
  auto source = test::random_generator(config, camera);
  save_model_file(s.dir / "m.flatnet", source, config, camera);
  // Another camera: other crop (24x28 planes), another initialisation of the first stage.
  auto other_camera = camera;
  other_camera.raw.crop = {0, 0, 24, 28};
  auto other_config = Config::load({}, {"model.unet.width=2", "model.inversion.init=random", "model.inversion.seed=5"});
  Generator fresh(generator_options(other_config, other_camera, true));
  Generator adapted(generator_options(other_config, other_camera, true));
  init_generator_from(s.dir / "m.flatnet", adapted, GeneratorPart::enhancer);
  const auto src = source->named_parameters(), mine = fresh->named_parameters();
  for (const auto& p : adapted->named_parameters()) {
    INFO(p.key());
    if (p.key().rfind("inversion.", 0) == 0)
      CHECK(torch::equal(p.value(), mine[p.key()]));  // this camera's, as initialised
    else
      CHECK(torch::equal(p.value(), src[p.key()]));  // the model's
  }
  // Copying everything cannot work across cameras: the first stage's shapes differ, named.
  Generator all(generator_options(other_config, other_camera, true));
  CHECK_THROWS_WITH(init_generator_from(s.dir / "m.flatnet", all), Contains("inversion.PhiL"));
}

TEST_CASE("transfer: the new camera's first stage reproduces the trained one's, W_new^T P_new = W_old^T P_old",
          "[model][adapt]") {
  test::Scratch s("transfer");
  auto config = Config::load({}, {"model.unet.width=2", "model.inversion.init=random", "model.inversion.shared=false"});
  const auto camera = test::tiny_camera();
  auto source = test::random_generator(config, camera);
  save_model_file(s.dir / "m.flatnet", source, config, camera);
  auto gen = at::detail::createCPUGenerator(3);
  const auto P_old = at::randn({4, 20, 16}, gen, torch::kFloat64), Q_old = at::randn({4, 24, 16}, gen, torch::kFloat64);
  const auto P_new = at::randn({4, 20, 16}, gen, torch::kFloat64), Q_new = at::randn({4, 24, 16}, gen, torch::kFloat64);
  Generator g(generator_options(config, camera, true));
  transfer_inversion(s.dir / "m.flatnet", {P_old, Q_old, P_new, Q_new}, 1e-9, g);
  const auto W_old = source->named_parameters()["inversion.PhiL"].to(torch::kFloat64);
  const auto W_new = g->named_parameters()["inversion.PhiL"].to(torch::kFloat64);
  for (int64_t c = 0; c < 4; ++c) {
    INFO(c);
    // P_new is 20x16 of full column rank: the products agree up to float32 rounding.
    const auto want = torch::matmul(W_old.select(2, c).t(), P_old[c]);
    const auto got = torch::matmul(W_new.select(2, c).t(), P_new[c]);
    CHECK((got - want).abs().max().item<double>() < 1e-4 * want.abs().max().item<double>());
  }
  // Regularisation shrinks it (lambda 1: every singular value at least halved in the filter).
  Generator h(generator_options(config, camera, true));
  transfer_inversion(s.dir / "m.flatnet", {P_old, Q_old, P_new, Q_new}, 1.0, h);
  CHECK(h->named_parameters()["inversion.PhiL"].norm().item<double>() <
        g->named_parameters()["inversion.PhiL"].norm().item<double>());
}
