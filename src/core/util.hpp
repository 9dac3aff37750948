#pragma once
// Small shared helpers: threads, atomic file output, text lists, progress reporting.
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

namespace flatnet {

namespace fs = std::filesystem;

// Where flatnet's shipped files are (configs/, models/, tests/data/golden): $FLATNET_DATA_DIR if
// set; else <executable>/../share/flatnet (an installed binary, `cmake --install`); else the
// folder above the executable when it holds configs/defaults.yaml (a build folder inside the source
// tree, as build/flatnet). Throws naming the places looked at when none holds the files.
std::filesystem::path data_dir();

// Keeps freed memory in the process (glibc: no mmap for blocks below 1 GiB, no heap trimming):
// called once by the CLI; every forward pass then reuses its buffers instead of page-faulting.
void keep_freed_memory();

// The cores this process may run on (its CPU affinity: `taskset -c 0,1` gives 2 on any machine;
// a container's cpuset likewise), at least 1. The one meaning of "all cores" in flatnet.
int all_cores();

// The cores of all_cores() that other work leaves free now, at least 1: the busy share of each
// allowed CPU over 50 ms (/proc/stat), summed and rounded, taken away. A thread on a core another
// job holds makes both wait (a training step 1.9x slower beside one busy core, docs/performance.md).
int free_cores();

// Sets LibTorch's intra-op threads; n <= 0 means free_cores(). Returns the count used.
int set_threads(int n);

// Writes a file atomically: `write_to` receives a temporary path in the same folder (same
// extension, so format detection by suffix still works); on success it is renamed onto `path`,
// on failure it is removed. A reader never sees a half-written file.
void write_atomically(const fs::path& path, const std::function<void(const fs::path&)>& write_to);
void write_text_atomically(const fs::path& path, const std::string& text);
// Bytes to a file, atomically; every write and the close are checked (errors name `path`).
void write_bytes_atomically(const fs::path& path, const std::string& bytes);

// A number's allowed range, for the tables that check flags (cli/common) and config keys
// (io/config) in one place each: {name, lowest, highest, what the range means}.
struct NumberRule {
  const char* name;
  double lo, hi;
  const char* meaning;
};
// "" when `text` is a finite number within the rule's range, else what is wrong
// ("is not a finite decimal number" or "is out of range").
std::string number_problem(const std::string& text, const NumberRule& rule);
// Whether `text` is a plain decimal number ("12", "-0.5", "2e-4"); hex, inf, nan and blanks are not.
bool is_decimal_number(const std::string& text);

// Reads a list file: one entry per line, CR/LF and surrounding blanks stripped, empty lines skipped.
std::vector<std::string> read_lines(const fs::path& path);

// Image files (by extension) in a folder, sorted by name. Errors if the folder is missing.
std::vector<fs::path> list_images(const fs::path& dir, const std::vector<std::string>& extensions);
bool has_extension(const fs::path& p, const std::vector<std::string>& extensions);
extern const std::vector<std::string> kImageExtensions;  // png jpg jpeg tif tiff bmp

// Calls fn(i) for i in [0, n) on `workers` threads (at least 1). After an exception no new index
// starts; the first exception is rethrown once all threads have finished.
// Each worker runs single-threaded (single_threaded_worker).
void parallel_for_index(int64_t n, int workers, const std::function<void(int64_t)>& fn);
// Call first in every worker thread flatnet starts. A new std::thread begins with OpenMP's initial
// thread count (all cores), not the count --threads set on the main thread, so each ATen or BLAS
// call in it would fork its own team: workers x cores threads on the cores. Worse, OpenBLAS's
// OpenMP build (Debian's libopenblas0-openmp) keeps one buffer set for multithreaded calls
// (NUM_PARALLEL=1), and two threads entering it at once may corrupt each other's GEMMs. A worker
// limited to one OpenMP thread takes OpenBLAS's single-threaded path, whose buffers are its own.
void single_threaded_worker();

// A whole file's bytes. Only regular files are read (a fifo or device is refused at once, never
// waited on), and a file over `max_bytes` is refused before anything that size is allocated.
// Errors name the file: missing, a folder, not a regular file, too large, unreadable.
constexpr uint64_t kMaxInputBytes = 16ull << 30;
// Model files and checkpoints: the paper-width generator's checkpoint with its moments is ~1.5 GB.
constexpr uint64_t kMaxModelFileBytes = 4ull << 30;
std::string read_file_text(const fs::path& path, uint64_t max_bytes = kMaxInputBytes);
std::vector<char> read_bytes(const fs::path& path, uint64_t max_bytes = kMaxInputBytes);
// The first `count` bytes of a file (all of it when it is shorter), with the same checks on what the
// file is: to tell a file's kind from its header without reading a model's weights.
std::string read_file_head(const fs::path& path, uint64_t count);
// The same checks without reading, for files a library opens itself (images, .mat, YAML): errors
// name a missing file, a folder, or a fifo, socket or device (which would block or never end).
void require_regular_file(const fs::path& path);

// Names that become one path component (a report's method and set names, a camera's name in a file
// name): non-empty, at most 128 bytes, no separator ('/' or '\\'), no control character, not hidden
// (a leading '.', which also rules out "." and ".."). A name is data, never a path: `flatnet report
// --methods ../x=M` must not write outside --out. Throws naming `what` and the name (escaped).
void require_plain_name(const std::string& name, const std::string& what);
// A string from a file or flag made safe to print on a terminal: control bytes (ESC, CR, BEL, ...) and
// DEL become \xNN, so a model file's metadata cannot move the cursor or retitle the window.
std::string printable(const std::string& text);

// Stable 64-bit hash (FNV-1a) for deterministic per-item seeds and content checksums.
uint64_t stable_hash(const std::string& s, uint64_t seed = 0);
uint64_t stable_hash(const void* data, size_t size, uint64_t seed = 0);
// A file's content as 16 hex digits (stable_hash of its bytes): what a cache or an output folder
// records of the file that made it, so that a changed file is never mistaken for the old one.
std::string file_fingerprint(const fs::path& path);
// SHA-256 of a file's bytes, 64 lowercase hex digits (as `sha256sum` prints it; OpenSSL's libcrypto),
// read in 1 MiB pieces. Errors name the file.
std::string sha256_hex(const fs::path& path);

// Ctrl-C / SIGTERM for the long loops (training, capture, collection, live view). After
// watch_interrupts(), a signal that arrives inside a FinishItemOnInterrupt scope turns interrupted()
// true and the loop finishes its current item (a training step, a frame) and saves; anywhere else it
// ends the process at once, with the signal's status (130, 143), as a second signal always does.
void watch_interrupts();
bool interrupted();
class FinishItemOnInterrupt {
 public:
  FinishItemOnInterrupt();
  ~FinishItemOnInterrupt();
  FinishItemOnInterrupt(const FinishItemOnInterrupt&) = delete;
  FinishItemOnInterrupt& operator=(const FinishItemOnInterrupt&) = delete;
};

// A one-line progress bar on stderr: "label  12/100 [#####     ] 3.2 it/s ETA 00:27".
class Progress {
 public:
  Progress(std::string label, int64_t total, bool enabled = true);
  void tick(int64_t n = 1);  // thread-safe
  void finish();
  double rate() const;  // items per second so far
  double elapsed_s() const;
  void set_status(std::string status);  // extra text after the bar (e.g. current losses)
  // A time budget that ends the job before `total` (training's train.minutes): the ETA shown is
  // the sooner of the two; with `total` 0 the budget alone, and the bar fills with the time spent.
  // Seconds from now.
  void set_time_left(double seconds);

 private:
  void draw(bool final_line);
  std::string label_, status_;
  int64_t total_;
  int64_t done_ = 0;
  bool enabled_;
  bool tty_;
  std::chrono::steady_clock::time_point start_, last_draw_;
  std::chrono::steady_clock::time_point deadline_{};  // unset: no budget
};

std::string format_duration(double seconds);

}  // namespace flatnet
