// Every command's flags from rows (cli/flag_rows.hpp, issue 91): the default a flag shows and uses
// is its struct's, a number is checked against its row's range, errors name the flag, and every
// command of the binary holds its flags to its structs (`flatnet options --check`).
#include "catch_torch.hpp"

#include <fstream>
#include <map>
#include <regex>

#include "cli/flag_rows.hpp"
#include "helpers.hpp"

using namespace flatnet;
using namespace flatnet::cli;
using Catch::Matchers::Contains;

namespace {

struct Settings {
  double rate = 0.25;
  int64_t count = 3;
  uint64_t seed = 7;
  bool force = false;
  std::string mode = "fast";
  std::filesystem::path out;
  bool loud = true;  // read through a FlagText as on|off
};

void set_loud(Settings& s, const std::string& text) {
  if (text != "on" && text != "off") throw std::invalid_argument("must be on or off");
  s.loud = text == "on";
}
std::string loud_text(const Settings& s) { return s.loud ? "on" : "off"; }

const FlagTable<Settings>& settings_flags() {
  static const FlagTable<Settings> rows = {
      {"rate", &Settings::rate, "a rate", 0, 1, "0 to 1"},
      {"count", &Settings::count, "a count", 1, 100, "1 to 100"},
      {"seed", &Settings::seed, "a seed"},
      {"force", &Settings::force, "a switch"},
      {"mode", &Settings::mode, "a mode"},
      {"out", &Settings::out, "a folder"},
      {"loud", FlagText<Settings>{set_loud, loud_text}, "on|off"},
  };
  return rows;
}

Settings parsed(std::vector<std::string> args) {
  cxxopts::Options o("test");
  add_flags(o, settings_flags());
  args.insert(args.begin(), "test");
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  const auto r = o.parse(static_cast<int>(argv.size()), argv.data());
  Settings s;
  read_flags(r, settings_flags(), s);
  return s;
}

}  // namespace

TEST_CASE("flag rows: the struct's defaults, every member set by its flag, errors naming the flag", "[cli][flags]") {
  const auto none = parsed({});
  CHECK(none.rate == 0.25);
  CHECK(none.count == 3);
  CHECK_FALSE(none.force);
  CHECK(none.loud);
  const auto all = parsed(
      {"--rate", "0.5", "--count", "9", "--seed", "11", "--force", "--mode", "slow", "--out", "a b", "--loud", "off"});
  CHECK(all.rate == 0.5);
  CHECK(all.count == 9);
  CHECK(all.seed == 11);
  CHECK(all.force);
  CHECK(all.mode == "slow");
  CHECK(all.out == "a b");
  CHECK_FALSE(all.loud);

  CHECK_THROWS_WITH(parsed({"--rate", "2"}), Contains("--rate: '2' is out of range: 0 to 1"));
  CHECK_THROWS_WITH(parsed({"--rate", "nan"}), Contains("--rate: 'nan' is not a finite decimal number"));
  CHECK_THROWS_WITH(parsed({"--count", "2.5"}), Contains("--count: '2.5' is not a whole number"));
  CHECK_THROWS_WITH(parsed({"--seed", "-1"}), Contains("--seed: '-1' is negative"));
  CHECK_THROWS_WITH(parsed({"--seed", "1e30"}), Contains("--seed: '1e30' is out of range for this setting"));
  CHECK_THROWS_WITH(parsed({"--loud", "maybe"}), Contains("--loud: 'maybe': must be on or off"));
  // A subnormal inside the range is a number (std::stod threw "stod" on it, issue 113).
  CHECK(parsed({"--rate", "1e-320"}).rate == std::strtod("1e-320", nullptr));
  CHECK_THROWS_WITH(parsed({"--count", "1e-320"}), Contains("--count: '1e-320' is out of range: 1 to 100"));

  // --help and `flatnet options --for` show the struct's defaults and the ranges.
  cxxopts::Options o("test");
  add_flags(o, settings_flags());
  const auto help = o.help();
  CHECK_THAT(help, Contains("a rate (default: 0.25) [0 to 1]") && Contains("a seed (default: 7)") &&
                       Contains("on|off (default: on)"));
  const auto described = describe_flags(settings_flags());
  REQUIRE(described.size() == 7);
  CHECK(described[3].is_switch);
  CHECK(described[6].default_text == "on");

  // A switch is false unless given: a row that binds a member defaulting to true is refused.
  struct On {
    bool on = true;
  };
  const FlagTable<On> bad = {{"on", &On::on, "a switch that defaults to on"}};
  cxxopts::Options o2("test");
  CHECK_THROWS_AS(add_flags(o2, bad), std::logic_error);
}

TEST_CASE("every command's flags agree with their structs, and no flag default is written by hand", "[cli][flags]") {
  auto r = test::run_flatnet("options --check");
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("every default is its struct's and every flag sets its member"));
  for (const std::string command : {"simulate",
                                    "calibrate",
                                    "recon",
                                    "eval",
                                    "eval fit-niqe",
                                    "report",
                                    "infer",
                                    "mask eval",
                                    "mask report",
                                    "mask camera",
                                    "bench",
                                    "demo",
                                    "capture",
                                    "capture-dataset",
                                    "capture-calibration",
                                    "live",
                                    "cameras",
                                    "train flags",
                                    "export",
                                    "import",
                                    "info",
                                    "options",
                                    "report inversion",
                                    "mask train",
                                    "mask separable",
                                    "every command"}) {
    INFO(command);
    const auto listed = test::run_flatnet("options --for '" + command + "'");
    CHECK(listed.code == 0);
  }
  r = test::run_flatnet("options --for infer --markdown");
  CHECK_THAT(r.output, Contains("| `--adapt-steps` | `0` |") && Contains("| `--batch` | `4` | 1 to 4096 per batch |") &&
                           Contains("| `--data-consistency` | `model` |") &&
                           Contains("| `--consistency-blur` | `model` |"));
  // The data-consistency step: the model's own unless given; off, or a number in range.
  const auto infer = "infer --model " + test::q(test::source_dir() / "models" / "flatnet-sim-transpose.flatnet") +
                     " --input /nonexistent --out /nonexistent ";
  r = test::run_flatnet(infer + "--data-consistency mdel");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--data-consistency") && Contains("'mdel'") && Contains("model, off, or a strength"));
  r = test::run_flatnet(infer + "--consistency-blur 65");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--consistency-blur") && Contains("out of range"));
  r = test::run_flatnet("options --for warp");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("'warp' is no command with flags") && Contains("mask camera"));
  // A default written beside a flag (cxxopts' default_value) would be a second truth: none in src/cli.
  for (const auto& e : std::filesystem::directory_iterator(test::source_dir() / "src" / "cli")) {
    std::ifstream in(e.path());
    const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    INFO(e.path());
    CHECK(text.find("default_value(") == std::string::npos);
  }
}

TEST_CASE("no flag is declared outside the rows: add_options appears only in the row machinery", "[cli][flags]") {
  // The row machinery (flag_rows.hpp's add_flags, commands.hpp's config rows, common.cpp's --help) may
  // call cxxopts' add_options; a command's file may not.
  const std::map<std::string, size_t> machinery = {{"flag_rows.hpp", 2}, {"commands.hpp", 2}, {"common.cpp", 1}};
  size_t files = 0;
  for (const auto& e : std::filesystem::directory_iterator(test::source_dir() / "src" / "cli")) {
    std::ifstream in(e.path());
    const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    size_t count = 0;
    for (auto at = text.find("add_options("); at != std::string::npos; at = text.find("add_options(", at + 1)) ++count;
    const auto name = e.path().filename().string();
    size_t allowed = 0;
    if (machinery.count(name)) allowed = machinery.at(name);
    INFO(name << " declares " << count << " flag groups by hand (allowed: " << allowed << ")");
    CHECK(count <= allowed);
    ++files;
  }
  CHECK(files > 10);
}
