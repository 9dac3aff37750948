// The manual's links: every relative link in README.md, docs/ and models/README.md names a file
// that exists, and every #anchor a heading of that file (GitHub's slugs).
#include "catch_torch.hpp"

#include <fstream>
#include <iomanip>
#include <regex>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "core/util.hpp"
#include "helpers.hpp"
#include "nn/model_file.hpp"

namespace {

std::vector<std::string> lines_of(const std::filesystem::path& p) {
  std::ifstream in(p);
  std::vector<std::string> out;
  for (std::string line; std::getline(in, line);) out.push_back(line);
  return out;
}

// GitHub's heading anchor: lower case; letters, digits, '-' and '_' kept; spaces become '-'; the rest dropped.
std::string slug(const std::string& heading) {
  std::string s;
  for (unsigned char c : heading) {
    if (std::isalnum(c) || c == '-' || c == '_')
      s += static_cast<char>(std::tolower(c));
    else if (c == ' ')
      s += '-';
    else if (c >= 0x80)
      s += static_cast<char>(c);  // UTF-8 letters are kept as they are
  }
  return s;
}

// Anchors of a Markdown file's headings (outside code fences).
std::set<std::string> anchors(const std::filesystem::path& p) {
  std::set<std::string> out;
  bool fence = false;
  for (const auto& line : lines_of(p)) {
    if (line.rfind("```", 0) == 0) fence = !fence;
    if (fence || line.empty() || line[0] != '#') continue;
    const auto text = line.substr(line.find_first_not_of('#'));
    out.insert(slug(text.substr(text.find_first_not_of(' '))));
  }
  return out;
}

struct Link {
  std::filesystem::path file;
  int line;
  std::string target;
};

std::vector<Link> links(const std::filesystem::path& p) {
  static const std::regex link(R"(\]\(([^)\s]+)\))");
  std::vector<Link> out;
  bool fence = false;
  int n = 0;
  for (const auto& line : lines_of(p)) {
    ++n;
    if (line.rfind("```", 0) == 0) fence = !fence;
    if (fence) continue;
    for (std::sregex_iterator it(line.begin(), line.end(), link), end; it != end; ++it)
      out.push_back({p, n, (*it)[1].str()});
  }
  return out;
}

std::vector<std::filesystem::path> manual_files() {
  const auto root = test::source_dir();
  std::vector<std::filesystem::path> files;
  for (const auto& dir : {root, root / "docs", root / "docs" / "results", root / "models"})
    for (const auto& e : std::filesystem::directory_iterator(dir))
      if (e.path().extension() == ".md") files.push_back(e.path());
  return files;
}

}  // namespace

TEST_CASE("the manual's relative links name files that exist and headings that exist", "[docs]") {
  const auto files = manual_files();
  REQUIRE(files.size() >= 8);  // README, models/README and the docs pages
  int checked = 0;
  for (const auto& file : files) {
    for (const auto& l : links(file)) {
      if (l.target.rfind("http://", 0) == 0 || l.target.rfind("https://", 0) == 0 || l.target.rfind("mailto:", 0) == 0)
        continue;
      INFO(l.file.string() << ":" << l.line << ": " << l.target);
      const auto hash = l.target.find('#');
      const auto path_part = l.target.substr(0, hash);
      const auto target = path_part.empty() ? l.file : l.file.parent_path() / path_part;
      CHECK(std::filesystem::exists(target));
      if (hash != std::string::npos && std::filesystem::exists(target) && target.extension() == ".md")
        CHECK(anchors(target).count(l.target.substr(hash + 1)) == 1);
      ++checked;
    }
  }
  CHECK(checked >= 20);
}

// The manual says how flatnet works today; dated runs belong to the results record (docs/results/).
// models/README.md is a manual page too; the model cards keep their own training history.
TEST_CASE("the manual's pages carry no dated lines and no earlier values, and the training how-to stays short",
          "[docs]") {
  static const std::regex date(R"(\b20[0-9][0-9]-[01][0-9]-[0-3][0-9]\b)");
  static const std::regex earlier(R"(\(was [0-9.-])");  // "4.54 (was 10.10)": the record keeps those
  const auto root = test::source_dir();
  int pages = 0;
  bool models_readme = false;
  for (const auto& file : manual_files()) {
    const bool card = file.parent_path() == root / "models" && file.filename() != "README.md";
    if (file.parent_path().filename() == "results" || card) continue;
    ++pages;
    models_readme = models_readme || file == root / "models" / "README.md";
    int n = 0;
    for (const auto& line : lines_of(file)) {
      ++n;
      INFO(file.string() << ":" << n << ": " << line);
      CHECK_FALSE(std::regex_search(line, date));
      CHECK_FALSE(std::regex_search(line, earlier));
    }
  }
  CHECK(models_readme);
  CHECK(pages >= 11);  // README, models/README and the docs pages
  CHECK(std::regex_search(std::string("| tikhonov | 4.54 (was 10.10) |"), earlier));
  CHECK(lines_of(root / "docs" / "training.md").size() <= 250);
  // The checker finds a date.
  CHECK(std::regex_search(std::string("Resumed on 2026-11-27 on the same Zen 3"), date));
  CHECK_FALSE(std::regex_search(std::string("version 1.13.1, 2 cores, 24 GiB"), date));
}

TEST_CASE("the link checker itself: slugs as GitHub makes them, and a broken link is found", "[docs]") {
  CHECK(slug("Shipped models (`models/flatnet-sim-*.flatnet`)") == "shipped-models-modelsflatnet-sim-flatnet");
  CHECK(slug("Precision: bf16 where the CPU has it") == "precision-bf16-where-the-cpu-has-it");
  test::Scratch s("docs_links");
  {
    std::ofstream f(s.dir / "a.md");
    f << "# Title\n## A section\nSee [b](b.md), [here](#a-section), [gone](#nowhere).\n```\n[not a link](x.md)\n```\n";
  }
  const auto found = links(s.dir / "a.md");
  REQUIRE(found.size() == 3);
  CHECK_FALSE(std::filesystem::exists(s.dir / found[0].target));
  CHECK(anchors(s.dir / "a.md").count("a-section") == 1);
  CHECK(anchors(s.dir / "a.md").count("nowhere") == 0);
}

TEST_CASE("README.md is the front door: short, with the two set-up commands and the manual's pages", "[docs]") {
  const auto readme = lines_of(test::source_dir() / "README.md");
  CHECK(readme.size() <= 200);
  std::string text;
  for (const auto& l : readme) text += l + "\n";
  CHECK(text.find("scripts/run.sh") != std::string::npos);
  CHECK(text.find("scripts/test.sh") != std::string::npos);
  for (const char* page : {"usage", "training", "evaluation", "deployment", "capture", "masks", "performance", "design",
                           "troubleshooting"}) {
    INFO(page);
    CHECK(text.find(std::string("docs/") + page + ".md") != std::string::npos);
  }
}

// docs/troubleshooting.md's headings quote the messages a user meets: each must still be in the source,
// so a message reworded in the code fails here until the page follows it.
TEST_CASE("every message docs/troubleshooting.md quotes is one flatnet prints", "[docs]") {
  const auto root = test::source_dir();
  std::string source;
  for (const auto& e : std::filesystem::recursive_directory_iterator(root / "src"))
    if (e.path().extension() == ".cpp" || e.path().extension() == ".hpp") {
      std::ifstream in(e.path());
      source += std::string(std::istreambuf_iterator<char>(in), {});
    }
  static const std::regex quoted(R"(^### `(.+)`$)");
  int messages = 0;
  for (const auto& line : lines_of(root / "docs" / "troubleshooting.md")) {
    std::smatch m;
    if (!std::regex_match(line, m, quoted)) continue;
    ++messages;
    INFO(m[1].str());
    CHECK(source.find(m[1].str()) != std::string::npos);
  }
  CHECK(messages >= 12);
  CHECK(source.find("a message no flatnet command prints") == std::string::npos);  // the search can fail
}

TEST_CASE("every shipped model has a card that matches its file: hash, held-out scores, the sections",
          "[docs][cards]") {
  int cards = 0;
  for (const auto& e : std::filesystem::directory_iterator(test::source_dir() / "models")) {
    if (e.path().extension() != ".flatnet") continue;
    const auto card = e.path().parent_path() / (e.path().stem().string() + ".md");
    INFO(card);
    REQUIRE(std::filesystem::exists(card));
    std::string text;
    for (const auto& l : lines_of(card)) text += l + "\n";
    // The Hugging Face layout: YAML front matter naming the model, then the card's sections.
    CHECK(text.rfind("---\n", 0) == 0);
    CHECK(text.find("- name: " + e.path().stem().string() + "\n") != std::string::npos);
    for (const char* section :
         {"## Intended use", "## Camera", "## Training data", "## Training\n", "## Evaluation", "## Limitations"})
      CHECK(text.find(section) != std::string::npos);
    // The card describes this file, not an earlier one: its hash and the scores the file records.
    CHECK(text.find("sha256 " + flatnet::sha256_hex(e.path())) != std::string::npos);
    const auto model = flatnet::load_model_file(e.path());
    REQUIRE_FALSE(model.provenance.scores.empty());
    const auto heldout = nlohmann::json::parse(model.provenance.scores).at("heldout");
    std::ostringstream psnr, ssim;
    psnr << std::fixed << std::setprecision(2) << heldout.at("psnr").get<double>();
    ssim << std::fixed << std::setprecision(3) << heldout.at("ssim").get<double>();
    CHECK(text.find("{type: psnr, value: " + psnr.str() + "}") != std::string::npos);
    CHECK(text.find("{type: ssim, value: " + ssim.str() + "}") != std::string::npos);
    CHECK(text.find("| held-out | " + psnr.str() + " | " + ssim.str() + " |") != std::string::npos);
    // A file that applies the capture's data-consistency step by default says so, and how to turn it off.
    if (model.spec.consistency_strength > 0) CHECK(text.find("`--data-consistency off`") != std::string::npos);
    ++cards;
  }
  CHECK(cards >= 2);
}

namespace {

// Functions defined at the file's top level (or in a namespace, not indented) whose bodies run past
// `limit` lines: a definition opens on a line that starts with a name and ends with '{', and closes
// at the first line that is '}' alone. Returns "file:line name (N lines)" for each.
std::vector<std::string> long_functions(const std::filesystem::path& file, size_t limit) {
  static const std::regex opening(R"(^[A-Za-z_].*\)( const)?( override)?( noexcept)? \{$)");
  std::vector<std::string> out;
  const auto lines = lines_of(file);
  size_t start = 0;
  bool open = false;
  for (size_t i = 0; i < lines.size(); ++i) {
    if (!open && std::regex_match(lines[i], opening) && lines[i].rfind("namespace", 0) != 0) {
      open = true;
      start = i;
    } else if (open && lines[i] == "}") {
      open = false;
      if (i - start > limit)
        out.push_back(file.string() + ":" + std::to_string(start + 1) + " " + lines[start].substr(0, 60) + " (" +
                      std::to_string(i - start) + " lines)");
    }
  }
  return out;
}

}  // namespace

TEST_CASE("the house: no function in src/ over 100 lines, and the stored-file container knows no model",
          "[docs][house]") {
  const auto src = test::source_dir() / "src";
  int files = 0;
  for (const auto& e : std::filesystem::recursive_directory_iterator(src)) {
    if (e.path().extension() != ".cpp") continue;
    ++files;
    for (const auto& f : long_functions(e.path(), 100)) FAIL_CHECK(f);
  }
  CHECK(files >= 50);
  for (const auto* name : {"stored_file.hpp", "stored_file.cpp"})
    for (const auto& line : lines_of(src / "nn" / name)) {
      INFO(name << ": " << line);
      CHECK(line.find("#include \"nn/model_file") == std::string::npos);
    }
  // The checker finds a long function.
  test::Scratch s("long_function");
  std::string text = "int f(int a) {\n";
  for (int i = 0; i < 101; ++i) text += "  a += 1;\n";
  text += "  return a;\n}\n";
  test::write_file(s.dir / "long.cpp", text);
  CHECK(long_functions(s.dir / "long.cpp", 100).size() == 1);
  CHECK(long_functions(s.dir / "long.cpp", 200).empty());
}
