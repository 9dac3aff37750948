#include "io/isolated_reader.hpp"

#include <fcntl.h>
#include <linux/audit.h>
#include <linux/filter.h>
#include <linux/seccomp.h>
#include <poll.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <climits>
#include <cstddef>
#include <cstring>
#include <fstream>
#include <vector>

#include "core/error.hpp"

#if defined(__SANITIZE_ADDRESS__)
#define FLATNET_UNDER_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define FLATNET_UNDER_ASAN 1
#endif
#endif
#if defined(FLATNET_UNDER_ASAN)
#include <sanitizer/common_interface_defs.h>
#endif

namespace flatnet {

namespace {

constexpr int kOutFd = 3;  // the pipe's write end in the child

// The system calls a parser needs once its file is open: reading it, memory, writing to the pipe,
// and ending (abort included). Every other call fails with EPERM: no open, no exec, no socket.
void allow_only_parsing_calls() {
#if defined(__x86_64__)
  static const int allowed[] = {SYS_read,       SYS_write,        SYS_pread64,        SYS_lseek,        SYS_fstat,
                                SYS_newfstatat, SYS_close,        SYS_mmap,           SYS_munmap,       SYS_mremap,
                                SYS_brk,        SYS_madvise,      SYS_mprotect,       SYS_futex,        SYS_exit,
                                SYS_exit_group, SYS_rt_sigreturn, SYS_rt_sigprocmask, SYS_rt_sigaction, SYS_tgkill,
                                SYS_gettid,     SYS_getpid,       SYS_clock_gettime,  SYS_sigaltstack,  SYS_sched_yield,
                                SYS_getrandom,  SYS_readv,        SYS_writev};
  std::vector<sock_filter> f;
  f.push_back(BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(seccomp_data, arch)));
  f.push_back(BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, AUDIT_ARCH_X86_64, 1, 0));
  f.push_back(BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_KILL_PROCESS));
  f.push_back(BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(seccomp_data, nr)));
  for (const int nr : allowed) {
    f.push_back(BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, static_cast<uint32_t>(nr), 0, 1));
    f.push_back(BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ALLOW));
  }
  f.push_back(BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ERRNO | (EPERM & SECCOMP_RET_DATA)));
  sock_fprog program{static_cast<unsigned short>(f.size()), f.data()};
  if (prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0 || prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, &program) != 0)
    _exit(3);  // no sandbox, no parsing
#endif
}

void write_all(int fd, const char* data, size_t size) {
  while (size > 0) {
    const ssize_t n = ::write(fd, data, size);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) _exit(4);
    data += n;
    size -= static_cast<size_t>(n);
  }
}

// The child's side: its limits, the parse, one status byte ('O' or 'E') and the bytes; never returns.
[[noreturn]] void run_child(int out, const IsolatedParse& parse, const IsolatedReadOptions& o, uint64_t vm_now) {
  if (dup2(out, kOutFd) < 0) _exit(5);
  // A crash ends the child with its signal, for the parent to report: not in a handler the parent
  // installed (libFuzzer's, which would file the parent's input as a finding of its own).
  for (const int sig : {SIGSEGV, SIGBUS, SIGABRT, SIGILL, SIGFPE, SIGTRAP, SIGXCPU}) signal(sig, SIG_DFL);
#if defined(FLATNET_UNDER_ASAN)
  __sanitizer_set_death_callback(nullptr);
#endif
  syscall(SYS_close_range, kOutFd + 1, UINT_MAX, 0);  // nothing of the parent's but stdio and the pipe
  // SIGXCPU at the soft limit (reported as such), SIGKILL a second later at the hard one.
  const rlimit cpu{static_cast<rlim_t>(o.cpu_seconds), static_cast<rlim_t>(o.cpu_seconds + 1)};
  setrlimit(RLIMIT_CPU, &cpu);
#if !defined(FLATNET_UNDER_ASAN)  // ASan reserves terabytes of address space
  const rlimit as{static_cast<rlim_t>(vm_now + o.max_memory_bytes), static_cast<rlim_t>(vm_now + o.max_memory_bytes)};
  setrlimit(RLIMIT_AS, &as);
#else
  (void)vm_now;
#endif
  std::string reply;
  try {
    reply = "O" + parse(allow_only_parsing_calls);
  } catch (const std::exception& e) {
    reply = std::string("E") + e.what();
  } catch (...) {
    reply = "Eunreadable";
  }
  write_all(kOutFd, reply.data(), reply.size());
  _exit(0);
}

uint64_t address_space_now() {
  std::ifstream statm("/proc/self/statm");
  uint64_t pages = 0;
  statm >> pages;
  return pages * static_cast<uint64_t>(sysconf(_SC_PAGESIZE));
}

// The parent's side: everything the child writes until it closes the pipe, within the limits.
std::string collect(int in, pid_t child, const std::filesystem::path& path, const IsolatedReadOptions& o) {
  std::string got;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(o.wall_seconds);
  std::vector<char> buffer(1 << 16);
  for (;;) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    pollfd p{in, POLLIN, 0};
    const int ready = left.count() > 0 ? poll(&p, 1, static_cast<int>(left.count())) : 0;
    if (ready < 0 && errno == EINTR) continue;
    if (ready <= 0) {
      kill(child, SIGKILL);
      throw Error(path, o.reader + " took longer than " + std::to_string(o.wall_seconds) +
                            " s and was stopped (a damaged or hostile file?)");
    }
    const ssize_t n = ::read(in, buffer.data(), buffer.size());
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return got;
    if (got.size() + static_cast<size_t>(n) > o.max_output_bytes + 1) {
      kill(child, SIGKILL);
      throw Error(path, o.reader + " handed back more than " + std::to_string(o.max_output_bytes) +
                            " bytes (a damaged or hostile file?)");
    }
    got.append(buffer.data(), static_cast<size_t>(n));
  }
}

std::string how_it_ended(int status) {
  if (WIFSIGNALED(status)) {
    const int sig = WTERMSIG(status);
    if (sig == SIGXCPU) return "ran out of its CPU time";
    return std::string("stopped with signal ") + std::to_string(sig) + " (" + strsignal(sig) + ")";
  }
  return "stopped with exit status " + std::to_string(WEXITSTATUS(status));
}

}  // namespace

std::string read_isolated(const std::filesystem::path& path, const IsolatedParse& parse,
                          const IsolatedReadOptions& options) {
  int fds[2];
  require(pipe2(fds, O_CLOEXEC) == 0, path, std::string("cannot start its reader: ") + std::strerror(errno));
  const uint64_t vm_now = address_space_now();
  const pid_t child = fork();
  if (child < 0) {
    close(fds[0]), close(fds[1]);
    throw Error(path, std::string("cannot start its reader: ") + std::strerror(errno));
  }
  if (child == 0) {
    close(fds[0]);
    run_child(fds[1], parse, options, vm_now);
  }
  close(fds[1]);
  std::string got;
  std::string failure;
  try {
    got = collect(fds[0], child, path, options);
  } catch (const Error& e) {
    failure = e.what();
  }
  close(fds[0]);
  int status = 0;
  while (waitpid(child, &status, 0) < 0 && errno == EINTR) {
  }
  if (!failure.empty()) throw Error(failure);
  const bool clean = WIFEXITED(status) && WEXITSTATUS(status) == 0 && !got.empty();
  require(clean, path, options.reader + " " + how_it_ended(status) + " (a damaged or hostile file?)");
  if (got[0] == 'E') throw Error(got.substr(1));
  return got.substr(1);
}

}  // namespace flatnet
