// What scripts/fuzz.sh found, kept: each input a harness (tests/fuzz/fuzz_*.cpp) once broke a reader
// with is read again the way that harness reads it, and must be refused with a flatnet::Error that
// names the file, before anything of the size it claims is allocated.
#include <algorithm>
#include <fstream>
#include <functional>

#include <fcntl.h>
#include <signal.h>
#include <unistd.h>

#include "core/error.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "io/dataset.hpp"
#include "io/image.hpp"
#include "io/isolated_reader.hpp"
#include "io/mat.hpp"
#include "optics/camera.hpp"
#include "catch_torch.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

std::filesystem::path finding(const std::string& name) { return test::data_dir() / "fuzz_findings" / name; }

// The harness's file: fuzz_image drops the first byte, which chose the extension (odd: .tif).
std::filesystem::path as_image(const test::Scratch& s, const std::string& name) {
  std::ifstream in(finding(name), std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)), {});
  REQUIRE(bytes.size() > 1);
  const auto path = s.dir / (bytes[0] % 2 ? "capture.tif" : "capture.png");
  std::ofstream(path, std::ios::binary) << bytes.substr(1);
  return path;
}

// Every reader of an image file, as fuzz_image calls them: each must refuse a bad header alike.
std::vector<std::function<void()>> image_readers(const std::filesystem::path& path) {
  return {[=] { read_rgb(path); }, [=] { read_gray16(path); }, [=] { read_image_header(path); }};
}

}  // namespace

TEST_CASE("fuzz finding: a 364-byte TIFF claiming 1.1 GB of samples is refused from its header", "[safe][fuzz]") {
  test::Scratch s("fuzz_image_finding");
  const auto path = as_image(s, "fuzz_image-tiff-claims-1gb.bin");
  for (const auto& read : image_readers(path))
    CHECK_THROWS_WITH(read(), Contains("capture.tif") && Contains("more than any compression holds"));
  // A real image of the same kind is still read: a flat 16-bit TIFF compresses well within the bound.
  write_gray16(s.dir / "flat.tif", torch::full({64, 80}, 1000, torch::kInt32));
  CHECK(read_gray16(s.dir / "flat.tif").size(1) == 80);
}

TEST_CASE("fuzz finding: a .mat struct whose field claims 520 M doubles is refused before matio reads it",
          "[safe][fuzz]") {
  // The struct's fields are checked as top-level variables are, when the file is opened.
  CHECK_THROWS_WITH(
      MatReader(finding("fuzz_mat-struct-field-claims-4gb.bin")),
      Contains("fuzz_mat-struct-field-claims-4gb.bin") && Contains("520093699 values") && Contains("its data holds 3"));
}

TEST_CASE("fuzz finding: a .mat whose header is neither v5 nor v7.3 never reaches matio's v4 reader", "[safe][fuzz]") {
  // 16 bytes before a v5 header moved its version field onto 0x0200 (v7.3), with no HDF5 file behind
  // it: matio then read the file as MATLAB v4 and took "MATL" for a name length (a 1.3 GB malloc).
  CHECK_THROWS_WITH(MatReader(finding("fuzz_mat-v73-flag-read-as-v4.bin")),
                    Contains("fuzz_mat-v73-flag-read-as-v4.bin") && Contains("MATLAB"));
  test::Scratch s("fuzz_mat_v4");
  // A v5 header with another version number, and a file of v4's layout: refused before matio alike.
  std::string v5(128, ' ');
  v5.replace(0, 19, "MATLAB 5.0 MAT-file");
  v5[124] = 0x03, v5[125] = 0x00, v5[126] = 'I', v5[127] = 'M';
  test::write_file(s.dir / "version.mat", v5);
  CHECK_THROWS_WITH(MatReader(s.dir / "version.mat"), Contains("version.mat") && Contains("v5"));
  std::string v4(200, '\0');
  v4.replace(16, 4, "MATL");
  test::write_file(s.dir / "v4.mat", v4);
  CHECK_THROWS_WITH(MatReader(s.dir / "v4.mat"), Contains("v4.mat") && Contains("does not begin with"));
}

TEST_CASE("fuzz finding: a .mat function handle claiming 6 x 69 M elements is refused before matio lists it",
          "[safe][fuzz]") {
  CHECK_THROWS_WITH(MatReader(finding("fuzz_mat-function-handle-claims-3gb.bin")),
                    Contains("fuzz_mat-function-handle-claims-3gb.bin") && Contains("MATLAB class 16"));
}

TEST_CASE("fuzz finding: a .mat struct whose name is not text, read as 0 fields here and 2^27 by matio, is refused",
          "[safe][fuzz]") {
  CHECK_THROWS_WITH(MatReader(finding("fuzz_mat-struct-name-not-text.bin")),
                    Contains("fuzz_mat-struct-name-not-text.bin") && Contains("name is not stored as text"));
}

TEST_CASE("fuzz finding: a list line naming a file the file system refuses is the list's error, with its line",
          "[safe][fuzz]") {
  test::Scratch s("fuzz_lists_finding");
  // As fuzz_dataset_lists splits its input: the measurement list, a NUL, the scene list.
  std::ifstream in(finding("fuzz_dataset_lists-name-too-long.bin"), std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  const auto cut = std::min(bytes.find('\0'), bytes.size());
  std::ofstream(s.dir / "train_meas.txt", std::ios::binary) << bytes.substr(0, cut);
  std::ofstream(s.dir / "train_gt.txt", std::ios::binary) << (cut < bytes.size() ? bytes.substr(cut + 1) : "");
  const DatasetLists lists{s.dir / "train_meas.txt", s.dir / "train_gt.txt", s.dir};
  CHECK_THROWS_AS(read_pairs(lists), Error);
  // The same with a plain name over the file system's 255-byte limit: the list and line are named.
  std::ofstream(s.dir / "train_meas.txt") << std::string(300, 'a') << ".png\n";
  std::ofstream(s.dir / "train_gt.txt") << "scene.png\n";
  CHECK_THROWS_WITH(read_pairs(lists),
                    Contains("train_meas.txt") && Contains("line 1") && Contains("File name too long"));
}

TEST_CASE("fuzz finding: a TIFF whose width reads back negative is refused from its header", "[safe][fuzz]") {
  test::Scratch s("fuzz_image_negative");
  const auto path = as_image(s, "fuzz_image-tiff-negative-width.bin");
  for (const auto& read : image_readers(path))
    CHECK_THROWS_WITH(read(), Contains("capture.tif") && Contains("an empty or impossible size"));
}

TEST_CASE("fuzz finding: a 384-byte .mat struct claiming 2^28 elements is refused before matio lists it",
          "[safe][fuzz]") {
  // matio makes a pointer per struct element when it lists the variables: 2 GB here. The file's
  // sizes are checked first: each element needs at least its tag in the file.
  CHECK_THROWS_WITH(
      MatReader(finding("fuzz_mat-struct-claims-2e28-elements.bin")),
      Contains("fuzz_mat-struct-claims-2e28-elements.bin") && Contains("declares") && Contains("elements in"));
  // A struct SciPy wrote (a field per element, as MATLAB does) is still listed and its numbers read.
  const auto scipy_struct = test::source_dir() / "tests" / "fuzz" / "corpus" / "fuzz_mat";
  int read = 0;
  for (const auto& entry : std::filesystem::directory_iterator(scipy_struct)) {
    MatReader mat(entry.path());
    read += static_cast<int>(mat.names().size());
  }
  CHECK(read > 0);
}

TEST_CASE("fuzz finding: YAML whose first token is a comma ends at once, not in an endless run of documents",
          "[safe][fuzz]") {
  // yaml-cpp 0.7's LoadAll loops for ever on it, its memory growing (the harness's timeout and an
  // earlier 2 GB stop): the text's documents are counted from parse events, stopping at 2.
  std::ifstream in(finding("fuzz_yaml-leading-comma-endless-documents.bin"), std::ios::binary);
  const std::string text((std::istreambuf_iterator<char>(in)), {});
  CHECK_THROWS_WITH(Config::from_text(text, "fuzz.yaml"), Contains("fuzz.yaml") && Contains("stray ','"));
  CHECK_THROWS_WITH(camera_from_yaml_text(text, "camera.yaml"), Contains("camera.yaml"));
  CHECK_THROWS_WITH(Config::from_text(", 2\n", "short.yaml"), Contains("short.yaml"));
  // One document, or none, still reads.
  CHECK(Config::from_text("train:\n  lr: 0.001\n", "one.yaml").num("train.lr") == 0.001);
  CHECK_NOTHROW(Config::from_text("# only a comment\n", "empty.yaml"));
}

TEST_CASE("fuzz finding: a TIFF claiming 18.6 M rows per strip is refused before its strip buffer is made",
          "[safe][fuzz]") {
  test::Scratch s("fuzz_image_strip");
  const auto path = as_image(s, "fuzz_image-tiff-rows-per-strip-2gb.bin");
  for (const auto& read : std::vector<std::function<void()>>{[&] { read_rgb(path); }, [&] { read_gray16(path); }})
    CHECK_THROWS_WITH(read(), Contains("capture.tif") && Contains("rows per strip"));
  // A TIFF as libtiff writes it (strips of a few rows) still reads.
  write_gray16(s.dir / "strips.tif", torch::full({300, 200}, 500, torch::kInt32));
  CHECK(read_gray16(s.dir / "strips.tif").size(0) == 300);
}

TEST_CASE(
    "fuzz finding: HDF5 overruns a heap buffer and reads a wild address in damaged v7.3 files; the child that "
    "parses them ends, flatnet does not",
    "[safe][fuzz]") {
  // Both were seeded from a v7.3 calibration matio wrote (tests/fuzz/corpus/fuzz_calibration/full73.mat):
  // libhdf5 1.10.8 (Debian 12) copied 64 bytes past a 92-byte buffer, and read from a wild address,
  // inside the flatnet process. Now HDF5 runs in an isolated child (io/isolated_reader.hpp): a crash
  // there is an Error naming the file, and what the child hands back is a value like any other.
  CameraConfig camera;  // the harness's tiny camera: 12x14 planes, 8-pixel scenes
  camera.raw.raw_height = 32, camera.raw.raw_width = 32;
  camera.raw.crop = {0, 0, 12, 14};
  camera.scene_size = 8;
  for (const char* name : {"fuzz_calibration-v73-hdf5-wild-read.bin", "fuzz_mat-v73-hdf5-heap-overflow.bin"}) {
    INFO(name);
    try {
      (void)load_calibration(finding(name), camera);
    } catch (const Error& e) {
      CHECK_THAT(std::string(e.what()), Contains(name));
    }
  }
}

TEST_CASE("an isolated reader: a crash, a throw, a file it may not open, a hog and a flood each end as an Error",
          "[safe][fuzz]") {
  const std::filesystem::path file = "parsed.bin";
  // What the parse returns comes back; what it throws comes back as the Error's text.
  CHECK(read_isolated(file, [](const std::function<void()>& lock_down) {
          lock_down();
          return std::string("values");
        }) == "values");
  CHECK_THROWS_WITH(read_isolated(file,
                                  [](const std::function<void()>&) -> std::string {
                                    throw Error(std::filesystem::path("parsed.bin"), "variable 'x' is damaged");
                                  }),
                    Contains("parsed.bin: variable 'x' is damaged"));
  // A crash ends the child only.
  CHECK_THROWS_WITH(read_isolated(file,
                                  [](const std::function<void()>&) -> std::string {
                                    raise(SIGSEGV);
                                    return "";
                                  }),
                    Contains("parsed.bin") && Contains("signal 11"));
  // Once locked down, the parser can open nothing (an HDF5 external link, an exploit's payload).
  const auto opened = read_isolated(file, [](const std::function<void()>& lock_down) {
    lock_down();
    const int fd = open("/etc/hostname", O_RDONLY);
    return std::string(fd < 0 && errno == EPERM ? "refused" : "opened");
  });
#if defined(__x86_64__)
  CHECK(opened == "refused");
#endif
  // A parser that spins is stopped by its CPU time; one that floods by the output bound.
  IsolatedReadOptions o;
  o.cpu_seconds = 1;
  CHECK_THROWS_WITH(read_isolated(
                        file,
                        [](const std::function<void()>& lock_down) -> std::string {
                          lock_down();
                          for (volatile uint64_t i = 0;; i = i + 1) {
                          }
                        },
                        o),
                    Contains("parsed.bin") && Contains("CPU time"));
  o.max_output_bytes = 1000;
  CHECK_THROWS_WITH(read_isolated(
                        file, [](const std::function<void()>&) { return std::string(5000, 'x'); }, o),
                    Contains("parsed.bin") && Contains("more than 1000 bytes"));
}
