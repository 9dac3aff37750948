#include "core/util.hpp"

#include "core/output_dir.hpp"

#include <algorithm>
#include <openssl/evp.h>

#include <malloc.h>

#include <cmath>

#include <atomic>
#include <csignal>

#include <fcntl.h>
#include <sched.h>  // sched_getaffinity
#include <sys/stat.h>
#include <unistd.h>

#include <fstream>
#include <iomanip>
#include <iostream>

#include <ATen/Parallel.h>       // at::set_num_threads
#include <dlfcn.h>               // dlsym: OpenMP's omp_set_num_threads
#include <c10/util/Exception.h>  // c10::Error
#include <atomic>
#include <mutex>
#include <cstring>
#include <map>
#include <regex>
#include <sstream>
#include <thread>

#include "core/error.hpp"

namespace flatnet {

const std::vector<std::string> kImageExtensions = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp"};

std::filesystem::path data_dir() {
  static const std::filesystem::path dir = [] {
    const auto has_files = [](const std::filesystem::path& d) {
      return std::filesystem::exists(d / "configs" / "defaults.yaml");
    };
    if (const char* env = std::getenv("FLATNET_DATA_DIR"); env && *env) {
      require(has_files(env), std::string("FLATNET_DATA_DIR=") + env,
              "holds no configs/defaults.yaml (it must name flatnet's share folder)");
      return std::filesystem::path(env);
    }
    std::error_code ec;
    const auto exe = std::filesystem::read_symlink("/proc/self/exe", ec);
    const auto bin = ec ? std::filesystem::path(".") : exe.parent_path();
    for (const auto& candidate : {bin.parent_path() / "share" / "flatnet", bin.parent_path()})
      if (has_files(candidate)) return candidate.lexically_normal();
    throw Error("flatnet's data files (configs/, models/) are neither in " +
                (bin.parent_path() / "share" / "flatnet").string() + " nor in " + bin.parent_path().string() +
                "; set FLATNET_DATA_DIR to the folder that holds them");
  }();
  return dir;
}

void keep_freed_memory() {
  // Tensors of 1-32 MB are allocated and freed on every forward pass. By default glibc serves them
  // with mmap and unmaps them on free, so each pass page-faults and zeroes its ~200 MB afresh:
  // 6-17 % of bf16 inference time at paper width (flatnet bench --rows infer_paper: 187 -> 156-176 ms
  // over runs).
  // Served from the heap, and the heap not trimmed, freed blocks are reused instead; the price is
  // ~100 MB more resident memory at paper width.
  mallopt(M_MMAP_THRESHOLD, 1 << 30);
  mallopt(M_TRIM_THRESHOLD, 1 << 30);
}

int all_cores() {
  cpu_set_t allowed;
  CPU_ZERO(&allowed);
  if (sched_getaffinity(0, sizeof(allowed), &allowed) == 0 && CPU_COUNT(&allowed) > 0) return CPU_COUNT(&allowed);
  return static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
}

namespace {

// Each CPU's busy and total ticks since boot, from /proc/stat's "cpuN user nice system idle iowait
// irq softirq steal" lines (idle and iowait are the idle ticks). Empty where it cannot be read.
std::map<int, std::pair<uint64_t, uint64_t>> cpu_ticks() {
  std::map<int, std::pair<uint64_t, uint64_t>> ticks;
  std::ifstream in("/proc/stat");
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("cpu", 0) != 0 || line.size() < 4 || !std::isdigit(static_cast<unsigned char>(line[3]))) continue;
    std::istringstream fields(line.substr(3));
    int cpu = -1;
    fields >> cpu;
    uint64_t value = 0, total = 0, idle = 0;
    for (int i = 0; i < 8 && fields >> value; ++i) {
      total += value;
      if (i == 3 || i == 4) idle += value;
    }
    if (cpu >= 0) ticks[cpu] = {total - idle, total};
  }
  return ticks;
}

}  // namespace

int free_cores() {
  cpu_set_t allowed;
  CPU_ZERO(&allowed);
  if (sched_getaffinity(0, sizeof(allowed), &allowed) != 0) return all_cores();
  // The kernel counts in ticks of 10 ms: 50 ms gives each CPU 5, enough to tell a core another job
  // holds (5 busy) from an idle one (0-1).
  const auto before = cpu_ticks();
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  const auto after = cpu_ticks();
  double busy = 0;  // cores' worth of other work on this process's CPUs
  int read = 0;
  for (const auto& [cpu, now] : after) {
    const auto then = before.find(cpu);
    if (cpu >= CPU_SETSIZE || !CPU_ISSET(cpu, &allowed) || then == before.end()) continue;
    const uint64_t total = now.second - then->second.second;
    if (total == 0) continue;
    busy += static_cast<double>(now.first - then->second.first) / static_cast<double>(total);
    ++read;
  }
  if (read == 0) return all_cores();
  return std::max(1, CPU_COUNT(&allowed) - static_cast<int>(std::lround(busy)));
}

int set_threads(int n) {
  if (n <= 0) n = free_cores();
  at::set_num_threads(n);
  return n;
}

void write_atomically(const fs::path& path, const std::function<void(const fs::path&)>& write_to) {
  require_claim_intact(path);  // before any folder is made: a removed run folder is not re-created
  if (path.has_parent_path()) {
    std::error_code ec;
    fs::create_directories(path.parent_path(), ec);
    require(!ec, path, "cannot make its folder " + path.parent_path().string() + " (" + ec.message() + ")");
  }
  static std::atomic<uint64_t> counter{0};
  const fs::path tmp = path.parent_path() / ("." + path.stem().string() + ".tmp" + std::to_string(::getpid()) + "_" +
                                             std::to_string(counter++) + path.extension().string());
  auto remove_tmp = [&] {
    std::error_code ec;
    fs::remove(tmp, ec);
  };
  // Whatever fails (our checks, LibTorch's writer, the file system), the temporary file goes and
  // the final name is neither created nor replaced.
  try {
    write_to(tmp);
    require_claim_intact(path);
    fs::rename(tmp, path);
  } catch (const Error&) {
    remove_tmp();
    throw;
  } catch (const c10::Error& e) {
    remove_tmp();
    throw Error(path, "write failed (disk full?): " + std::string(e.what_without_backtrace()).substr(0, 120));
  } catch (const fs::filesystem_error& e) {
    remove_tmp();
    throw Error(path, "write failed: " + e.code().message());
  } catch (...) {
    remove_tmp();
    throw;
  }
}

void write_bytes_atomically(const fs::path& path, const std::string& bytes) {
  write_atomically(path, [&](const fs::path& tmp) {
    std::ofstream out(tmp, std::ios::binary);
    require(static_cast<bool>(out), path, "cannot open for writing");
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    out.close();
    require(static_cast<bool>(out), path, "write failed (disk full?)");
  });
}

void write_text_atomically(const fs::path& path, const std::string& text) { write_bytes_atomically(path, text); }

std::vector<std::string> read_lines(const fs::path& path) {
  std::istringstream in(read_file_text(path, 1ull << 30));  // a regular file: a fifo would block
  std::vector<std::string> lines;
  std::string line;
  while (std::getline(in, line)) {
    const auto first = line.find_first_not_of(" \t\r\n");
    if (first == std::string::npos) continue;
    const auto last = line.find_last_not_of(" \t\r\n");
    lines.push_back(line.substr(first, last - first + 1));
  }
  return lines;
}

bool has_extension(const fs::path& p, const std::vector<std::string>& extensions) {
  std::string ext = p.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  return std::find(extensions.begin(), extensions.end(), ext) != extensions.end();
}

std::vector<fs::path> list_images(const fs::path& dir, const std::vector<std::string>& extensions) {
  require(fs::is_directory(dir), dir,
          fs::exists(dir) ? "not a folder"
                          : "no such folder (the shipped configs read the photographs from "
                            "../shared/data/images/train beside the checkout)");
  std::vector<fs::path> files;
  for (const auto& e : fs::directory_iterator(dir)) {
    const auto name = e.path().filename().string();
    if (e.is_regular_file() && !name.empty() && name[0] != '.' && has_extension(e.path(), extensions))
      files.push_back(e.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

uint64_t stable_hash(const void* data, size_t size, uint64_t seed) {
  uint64_t h = 1469598103934665603ull ^ (seed * 0x9E3779B97F4A7C15ull);
  const auto* p = static_cast<const unsigned char*>(data);
  for (size_t i = 0; i < size; ++i) {
    h ^= p[i];
    h *= 1099511628211ull;
  }
  return h;
}

uint64_t stable_hash(const std::string& s, uint64_t seed) { return stable_hash(s.data(), s.size(), seed); }

namespace {
std::atomic<bool> g_interrupted{false};
std::atomic<int> g_items_in_progress{0};  // live FinishItemOnInterrupt scopes
// Inside a FinishItemOnInterrupt scope, the first Ctrl-C or SIGTERM asks the loop to finish its item
// and save; a second one ends the process at once (a user who presses Ctrl-C twice means it).
// Outside one (loading files, parsing configs, writing results), there is nothing to finish: the
// signal's default action ends the process at once (exit status 130 or 143).
void on_interrupt_signal(int sig) {
  if (g_items_in_progress.load() > 0 && !g_interrupted.exchange(true)) return;
  std::signal(sig, SIG_DFL);
  std::raise(sig);
}
}  // namespace

void watch_interrupts() {
  g_interrupted = false;
  std::signal(SIGINT, on_interrupt_signal);
  std::signal(SIGTERM, on_interrupt_signal);
}

FinishItemOnInterrupt::FinishItemOnInterrupt() { ++g_items_in_progress; }
FinishItemOnInterrupt::~FinishItemOnInterrupt() { --g_items_in_progress; }

bool interrupted() { return g_interrupted; }

std::string format_duration(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0) return "--:--";
  const auto s = static_cast<int64_t>(seconds + 0.5);
  std::ostringstream os;
  if (s >= 3600) os << s / 3600 << ":";
  os << std::setw(2) << std::setfill('0') << (s / 60) % 60 << ":" << std::setw(2) << s % 60;
  return os.str();
}

namespace {
std::mutex g_progress_mutex;
}

Progress::Progress(std::string label, int64_t total, bool enabled)
    : label_(std::move(label)),
      total_(total),
      enabled_(enabled),
      tty_(::isatty(2) != 0),
      start_(std::chrono::steady_clock::now()),
      last_draw_(start_) {}

double Progress::elapsed_s() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

double Progress::rate() const {
  const double t = elapsed_s();
  return t > 0 ? done_ / t : 0.0;
}

void Progress::tick(int64_t n) {
  std::lock_guard<std::mutex> lock(g_progress_mutex);
  done_ += n;
  const auto now = std::chrono::steady_clock::now();
  // Redraw at most 5x/s on a terminal, every 10 s in a log file.
  const double interval = tty_ ? 0.2 : 10.0;
  if (std::chrono::duration<double>(now - last_draw_).count() >= interval) {
    last_draw_ = now;
    draw(false);
  }
}

void Progress::set_status(std::string status) {
  std::lock_guard<std::mutex> lock(g_progress_mutex);
  status_ = std::move(status);
}

void Progress::finish() {
  std::lock_guard<std::mutex> lock(g_progress_mutex);
  draw(true);
}

void Progress::set_time_left(double seconds) {
  deadline_ = std::chrono::steady_clock::now() +
              std::chrono::duration_cast<std::chrono::steady_clock::duration>(std::chrono::duration<double>(seconds));
}

void Progress::draw(bool final_line) {
  if (!enabled_) return;
  const double r = rate();
  const int width = 24;
  const bool has_deadline = deadline_ != std::chrono::steady_clock::time_point{};
  const double budget_left =
      has_deadline ? std::max(0.0, std::chrono::duration<double>(deadline_ - std::chrono::steady_clock::now()).count())
                   : 0;
  // No count to reach (total 0) but a deadline: the bar fills with the time spent.
  double share = total_ > 0 ? static_cast<double>(std::min<int64_t>(done_, total_)) / total_ : 0;
  if (total_ <= 0 && has_deadline) share = final_line ? 1 : elapsed_s() / std::max(1e-9, elapsed_s() + budget_left);
  const int filled = static_cast<int>(width * std::clamp(share, 0.0, 1.0));
  std::ostringstream os;
  os << label_ << " " << done_;
  if (total_ > 0) os << "/" << total_;
  os << " [" << std::string(filled, '#') << std::string(width - filled, ' ') << "] " << std::fixed
     << std::setprecision(1) << r << " it/s";
  if (final_line)
    os << " in " << format_duration(elapsed_s());
  else {
    double eta = r > 0 && total_ > 0 ? (total_ - done_) / r : -1;
    if (has_deadline) eta = eta < 0 ? budget_left : std::min(eta, budget_left);
    os << " ETA " << format_duration(eta);
  }
  if (!status_.empty()) os << "  " << status_;
  if (tty_)
    std::cerr << "\r" << os.str() << "\033[K" << (final_line ? "\n" : "") << std::flush;
  else
    std::cerr << os.str() << "\n" << std::flush;
}

void single_threaded_worker() {
  // Looked up at run time: the OpenMP runtime is LibTorch's (libgomp), and a LibTorch built without
  // OpenMP has none to limit.
  using SetNumThreads = void (*)(int);
  static const auto set_num_threads = reinterpret_cast<SetNumThreads>(::dlsym(RTLD_DEFAULT, "omp_set_num_threads"));
  // ATen sets a new thread's count from --threads on its first parallel call (a thread-local
  // lazy init); run that first, or it would undo this later.
  (void)at::get_num_threads();
  if (set_num_threads) set_num_threads(1);
}

void parallel_for_index(int64_t n, int workers, const std::function<void(int64_t)>& fn) {
  std::atomic<int64_t> next{0};
  std::atomic<bool> failed{false};
  std::exception_ptr error;
  std::mutex error_mutex;
  std::vector<std::thread> pool;
  for (int t = 0; t < std::max(1, workers); ++t)
    pool.emplace_back([&] {
      single_threaded_worker();
      for (int64_t i; !failed && (i = next++) < n;) {
        try {
          fn(i);
        } catch (...) {
          std::lock_guard<std::mutex> lock(error_mutex);
          if (!error) error = std::current_exception();
          failed = true;
        }
      }
    });
  for (auto& t : pool) t.join();
  if (error) std::rethrow_exception(error);
}

namespace {

// An open regular file (a fifo or device is refused at once, never waited on) and its size.
struct RegularFile {
  int fd = -1;
  uint64_t size = 0;
  int64_t blocks = 0;
  RegularFile(const RegularFile&) = delete;
  RegularFile& operator=(const RegularFile&) = delete;
  explicit RegularFile(const fs::path& path) {
    // O_NONBLOCK: opening a fifo must not wait for a writer; it is refused below, like a device.
    fd = ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) {
      const int err = errno;
      require(err != ENOENT, path, "no such file");
      throw Error(path, std::string("cannot be opened for reading (") + std::strerror(err) + ")");
    }
    struct stat st {};
    const bool examined = ::fstat(fd, &st) == 0;
    if (!examined || !S_ISREG(st.st_mode)) {
      ::close(fd);  // the destructor does not run when the constructor throws
      require(examined, path, "cannot be examined (fstat failed)");
      require(!S_ISDIR(st.st_mode), path, "is a folder, not a file");
      throw Error(path, "is not a regular file (a fifo, socket or device); flatnet reads only files");
    }
    size = static_cast<uint64_t>(st.st_size);
    blocks = static_cast<int64_t>(st.st_blocks);
  }
  ~RegularFile() { ::close(fd); }

  // The first `count` bytes (count <= size), into memory allocated here.
  std::string read(const fs::path& path, uint64_t count) const {
    std::string bytes;
    try {
      bytes.assign(count, '\0');
    } catch (const std::bad_alloc&) {
      throw Error(path, "is " + std::to_string(count) + " bytes; there is not enough memory to read it");
    }
    size_t done = 0;
    while (done < count) {
      const auto n = ::read(fd, bytes.data() + done, count - done);
      if (n < 0 && errno == EINTR) continue;
      require(n >= 0, path, std::string("read failed (") + std::strerror(errno) + ")");
      if (n == 0) break;  // the file shrank while being read
      done += static_cast<size_t>(n);
    }
    require(done == count, path, "changed size while being read");
    return bytes;
  }
};

}  // namespace

std::string read_file_text(const fs::path& path, uint64_t max_bytes) {
  const RegularFile file(path);
  require(file.size <= max_bytes, path,
          "is " + std::to_string(file.size) + " bytes, over the limit of " + std::to_string(max_bytes) +
              " for this kind of file");
  // A sparse file (holes that read as zeros) claims a size its disk blocks do not hold: 5 GiB of
  // nothing would be allocated and read. Real files fill their blocks (compression aside: 1/8).
  const auto on_disk = static_cast<uint64_t>(file.blocks) * 512;
  require(file.size <= (64ull << 20) || on_disk >= file.size / 8, path,
          "is sparse: it claims " + std::to_string(file.size) + " bytes and holds " + std::to_string(on_disk) +
              " on disk (a damaged or hostile file)");
  return file.read(path, file.size);
}

std::string read_file_head(const fs::path& path, uint64_t count) {
  const RegularFile file(path);
  return file.read(path, std::min(count, file.size));
}

std::string file_fingerprint(const fs::path& path) {
  const auto bytes = read_file_text(path);
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(stable_hash(bytes.data(), bytes.size())));
  return hex;
}

std::string sha256_hex(const fs::path& path) {
  require_regular_file(path);
  std::ifstream in(path, std::ios::binary);
  require(in.good(), path, "cannot be opened for reading");
  std::unique_ptr<EVP_MD_CTX, decltype(&EVP_MD_CTX_free)> ctx(EVP_MD_CTX_new(), EVP_MD_CTX_free);
  require(ctx && EVP_DigestInit_ex(ctx.get(), EVP_sha256(), nullptr) == 1, path, "SHA-256 unavailable (OpenSSL)");
  std::vector<char> piece(1 << 20);
  while (in) {
    in.read(piece.data(), static_cast<std::streamsize>(piece.size()));
    if (in.gcount() > 0) EVP_DigestUpdate(ctx.get(), piece.data(), static_cast<size_t>(in.gcount()));
  }
  require(in.eof(), path, "read error while hashing");
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_DigestFinal_ex(ctx.get(), digest, &length);
  std::string hex;
  char byte[3];
  for (unsigned int i = 0; i < length; ++i) {
    std::snprintf(byte, sizeof byte, "%02x", digest[i]);
    hex += byte;
  }
  return hex;
}

void require_regular_file(const fs::path& path) {
  std::error_code ec;
  const auto st = fs::status(path, ec);
  require(fs::exists(st), path, "no such file");
  require(!fs::is_directory(st), path, "is a folder, not a file");
  require(fs::is_regular_file(st), path, "is not a regular file (a fifo, socket or device); flatnet reads only files");
}

std::vector<char> read_bytes(const fs::path& path, uint64_t max_bytes) {
  const auto text = read_file_text(path, max_bytes);
  return std::vector<char>(text.begin(), text.end());
}

bool is_decimal_number(const std::string& text) {
  // [+-] digits [. digits] [e [+-] digits]: what a config or flag means by a number. strtod would
  // also take hex ("0x10" -> 16), "inf", "nan" and leading blanks.
  static const std::regex decimal(R"([+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?)");
  return std::regex_match(text, decimal);
}

std::string number_problem(const std::string& text, const NumberRule& rule) {
  if (!is_decimal_number(text)) return "is not a finite decimal number";
  const double v = std::strtod(text.c_str(), nullptr);
  if (!std::isfinite(v)) return "is not a finite decimal number";
  if (v < rule.lo || v > rule.hi) return "is out of range";
  return "";
}

std::string printable(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  for (const unsigned char c : text) {
    if (c < 0x20 || c == 0x7f) {
      char hex[5];
      std::snprintf(hex, sizeof hex, "\\x%02x", c);
      out += hex;
    } else {
      out += static_cast<char>(c);
    }
  }
  return out;
}

void require_plain_name(const std::string& name, const std::string& what) {
  auto refuse = [&](const std::string& why) {
    throw Error(
        what, "'" + printable(name) + "' " + why + "; a name becomes one file or folder name inside the output folder");
  };
  if (name.empty()) refuse("is empty");
  if (name.size() > 128) refuse("is longer than 128 bytes");
  if (name.find('/') != std::string::npos || name.find('\\') != std::string::npos) refuse("holds a path separator");
  if (name.front() == '.') refuse("starts with '.' (hidden, or a parent folder)");
  for (const unsigned char c : name)
    if (c < 0x20 || c == 0x7f) refuse("holds a control character");
}

}  // namespace flatnet
