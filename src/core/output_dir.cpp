#include "core/output_dir.hpp"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <fstream>
#include <mutex>
#include <sstream>
#include <vector>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {
namespace {

namespace fs = std::filesystem;

struct Marker {
  std::string command, settings;
};

std::string marker_text(const OutputRole& role) {
  return "# written by flatnet: this folder holds the output of one command; see README (output folders)\n"
         "command: " +
         role.command + "\nsettings: " + role.settings + "\n";
}

bool read_marker(const fs::path& dir, Marker& m) {
  const auto path = dir / kOutputMarker;
  if (!fs::exists(path)) return false;
  std::istringstream in(read_file_text(path, 1 << 16));
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("command: ", 0) == 0) m.command = line.substr(9);
    if (line.rfind("settings: ", 0) == 0) m.settings = line.substr(10);
  }
  return true;
}

// The folder's entries other than flatnet's own marker and lock: how many, and one name.
std::pair<size_t, std::string> foreign_entries(const fs::path& dir) {
  size_t n = 0;
  std::string example;
  for (const auto& e : fs::directory_iterator(dir)) {
    const auto name = e.path().filename().string();
    if (name == kOutputMarker || name == kOutputLock) continue;
    if (example.empty()) example = name;
    ++n;
  }
  return {n, example};
}

int lock_folder(const fs::path& dir, const OutputRole& role) {
  const auto path = dir / kOutputLock;
  // O_NOFOLLOW: a lock that is a symlink (planted, or copied in) is refused, never followed, so no
  // file outside the folder is truncated or written; O_NONBLOCK: a fifo does not block the open.
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK | O_NOCTTY, 0644);
  if (fd < 0 && errno == ELOOP)
    throw Error(path, "is a symbolic link; flatnet never writes through links it did not make (remove it)");
  require(fd >= 0, path, std::string("cannot be created (") + std::strerror(errno) + ")");
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode) || st.st_nlink > 1) {
    ::close(fd);
    throw Error(path, "is not a plain file of its own (a fifo, device or hard link); remove it");
  }
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    std::string holder(512, '\0');
    const auto n = ::pread(fd, holder.data(), holder.size(), 0);
    holder.resize(n > 0 ? static_cast<size_t>(n) : 0);
    while (!holder.empty() && (holder.back() == '\n' || holder.back() == '\0')) holder.pop_back();
    ::close(fd);
    throw Error(dir, "another flatnet command is writing to this folder" +
                         (holder.empty() ? std::string() : " (" + holder + ")") +
                         "; wait for it to finish or choose another folder");
  }
  const auto who = "pid " + std::to_string(::getpid()) + ", flatnet " + role.command + "\n";
  if (::ftruncate(fd, 0) != 0 || ::pwrite(fd, who.data(), who.size(), 0) < 0) {
    // The lock holds without the note; the note only helps the message above.
  }
  return fd;
}

// Removes `dir` only if it is empty (rmdir): never anything another command wrote into it.
void remove_if_empty(const fs::path& dir) {
  std::error_code not_empty;
  fs::remove(dir, not_empty);
}

// The folders this process holds claims on, and the descriptor of each one's locked file.
struct HeldFolder {
  fs::path dir;  // absolute, lexically normal
  int fd;
};
std::mutex held_mutex;
std::vector<HeldFolder> held_folders;

fs::path normal_absolute(const fs::path& p) {
  std::error_code ec;
  auto n = fs::absolute(p, ec);
  n = (ec ? p : n).lexically_normal();
  // "RUN/" names the folder RUN: its empty last component would match no file inside it.
  if (!n.has_filename() && n.has_relative_path()) n = n.parent_path();
  return n;
}

void hold(const fs::path& dir, int fd) {
  std::lock_guard<std::mutex> lock(held_mutex);
  held_folders.push_back({normal_absolute(dir), fd});
}

void unhold(int fd) {
  std::lock_guard<std::mutex> lock(held_mutex);
  held_folders.erase(
      std::remove_if(held_folders.begin(), held_folders.end(), [fd](const HeldFolder& h) { return h.fd == fd; }),
      held_folders.end());
}

// Whether `dir`'s lock file is the very file `fd` locked (same device and inode).
bool lock_is_ours(const fs::path& dir, int fd) {
  struct stat held = {};
  struct stat now = {};
  if (::fstat(fd, &held) != 0) return false;
  if (::lstat((dir / kOutputLock).c_str(), &now) != 0) return false;
  return held.st_dev == now.st_dev && held.st_ino == now.st_ino;
}

}  // namespace

void require_claim_intact(const fs::path& file) {
  std::lock_guard<std::mutex> lock(held_mutex);
  if (held_folders.empty()) return;
  // The innermost held folder that holds `file` (walking up from the file); the write passes if a
  // claim on it still holds its lock (one process claims a folder once, unless it was removed and
  // claimed again).
  for (auto dir = normal_absolute(file).parent_path();; dir = dir.parent_path()) {
    const auto on_dir = [&](const HeldFolder& h) { return h.dir == dir; };
    if (std::any_of(held_folders.begin(), held_folders.end(), on_dir)) {
      const bool intact = std::any_of(held_folders.begin(), held_folders.end(),
                                      [&](const HeldFolder& h) { return on_dir(h) && lock_is_ours(h.dir, h.fd); });
      require(intact, dir,
              "was removed, moved or replaced while this flatnet command wrote to it (its " + std::string(kOutputLock) +
                  " is no longer this command's); nothing more is written there, so no other command's files are "
                  "overwritten (" +
                  file.filename().string() + " not written)");
      return;
    }
    if (dir == dir.parent_path()) return;  // the root: `file` is in no held folder
  }
}

OutputClaim::OutputClaim(OutputClaim&& other) noexcept { *this = std::move(other); }

OutputClaim& OutputClaim::operator=(OutputClaim&& other) noexcept {
  if (this != &other) {
    release();
    fd_ = other.fd_;
    existed_ = other.existed_;
    dir_ = other.dir_;
    created_dir_ = other.created_dir_;
    wrote_marker_ = other.wrote_marker_;
    exceptions_at_claim_ = other.exceptions_at_claim_;
    other.fd_ = -1;
    other.dir_.clear();
  }
  return *this;
}

OutputClaim::~OutputClaim() { release(); }

void OutputClaim::release() noexcept {
  if (fd_ < 0) return;
  try {
    const bool failing = std::uncaught_exceptions() > exceptions_at_claim_;
    // Undone only while the folder is still the one this claim locked (a folder removed and
    // re-claimed by another run holds that run's marker and lock), and only file by file: our
    // marker, our lock, then the folder if that left it empty. Nothing else is ever removed.
    if (failing && wrote_marker_ && lock_is_ours(dir_, fd_) && foreign_entries(dir_).first == 0) {
      fs::remove(dir_ / kOutputMarker);
      fs::remove(dir_ / kOutputLock);
      if (created_dir_) remove_if_empty(dir_);
    }
  } catch (...) {
    // Best effort: the claim's own files stay.
  }
  unhold(fd_);
  ::close(fd_);  // closing drops the flock
  fd_ = -1;
}

OutputClaim claim_output_folder(const fs::path& dir, const OutputRole& role) {
  require_option(!dir.empty(), "output_role.dir", "an output folder is required");
  OutputClaim claim;
  claim.dir_ = dir;
  claim.exceptions_at_claim_ = std::uncaught_exceptions();
  if (fs::exists(dir)) {
    require(fs::is_directory(dir), dir, "exists and is not a folder");
  } else {
    // True only for the command whose mkdir made it: of two started at once on a new folder, the
    // other one does not count it as its own.
    claim.created_dir_ = fs::create_directories(dir);
  }
  try {
    claim.fd_ = lock_folder(dir, role);
  } catch (...) {
    // Refused (e.g. the other command of such a pair holds the lock): the folder goes only if it is
    // still empty, never with the files of the command that holds it.
    if (claim.created_dir_) remove_if_empty(dir);
    throw;
  }  // before reading the marker: no other command changes it now
  hold(dir, claim.fd_);
  Marker m;
  bool marked = read_marker(dir, m);
  if (!marked && !role.own_file.empty() && fs::exists(dir / role.own_file)) {
    marked = true;  // an older flatnet's output of this command: adopted as it is
    m.command = role.command;
    m.settings = role.settings;
  }
  const auto [foreign, example] = foreign_entries(dir);
  const auto hint = role.force ? std::string()
                               : std::string("; choose another folder, or add " + option_key("output_role.force") +
                                             " to write into it anyway");
  if (marked && m.command != role.command && !role.force)
    throw Error(dir, "holds the output of `flatnet " + m.command + "`, not of `flatnet " + role.command + "`" + hint);
  if (marked && m.command == role.command && !role.settings.empty() && m.settings != role.settings && !role.force)
    throw Error(dir, "holds `flatnet " + m.command + "` output made with other settings (" + m.settings + "; now " +
                         role.settings + ")" + hint);
  if (!marked && foreign > 0 && !role.force)
    throw Error(dir, "holds " + std::to_string(foreign) + " entries flatnet did not write (such as '" + example +
                         "'); flatnet writes only into new or empty folders and its own" + hint);
  claim.existed_ = marked && m.command == role.command;
  if (!marked || m.command != role.command || m.settings != role.settings) {
    write_text_atomically(dir / kOutputMarker, marker_text(role));
    claim.wrote_marker_ = !marked;
  }
  return claim;
}

}  // namespace flatnet
