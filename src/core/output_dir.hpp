#pragma once
// Output folders: what flatnet writes never replaces what it did not write for that role, and two
// commands never write one folder at once (issue 25).
//
// A folder flatnet writes holds `.flatnet-output`: the command that made it (its role, e.g. "infer")
// and the settings its contents depend on (e.g. the model's content hash). Claiming a folder:
//  - a new or empty folder is created and marked;
//  - a folder marked for the same role and settings is written again (reruns, --resume);
//  - a folder marked for another role, or for the same role with other settings, or one that holds
//    files but no mark (a dataset's gt/, raw captures, photographs) is refused with a message that
//    names what is there; `force` writes into it anyway and re-marks it;
//  - while a command holds the claim, the folder is locked (flock on `.flatnet-lock`, which names the
//    holder): a second command is refused at once, whatever `force` says. The kernel drops the lock
//    when the process ends, however it ends.
//  - every atomic write into a held folder (core/util.hpp: checkpoints, models, tables) first checks
//    that the folder's lock is still the one the claim holds. A folder removed, moved or replaced
//    while its command ran (a user's `rm -rf RUN` and a new run started there) is written no more:
//    the write is refused, instead of the old command re-creating the folder or overwriting the
//    new command's files.
#include <filesystem>
#include <string>

namespace flatnet {

struct OutputRole {
  std::string command;   // "infer", "train", "mask train", ...
  std::string settings;  // what the contents depend on; "" when reruns may change anything
  bool force = false;    // write into a folder that fails the rules above (never past another's lock)
  // A file whose presence marks an unmarked folder as this command's own (folders written before
  // markers existed: a run's latest.ckpt, a dataset's simulate.yaml); "" for none.
  std::string own_file;
};

class OutputClaim {
 public:
  OutputClaim() = default;
  OutputClaim(const OutputClaim&) = delete;
  OutputClaim& operator=(const OutputClaim&) = delete;
  OutputClaim(OutputClaim&& other) noexcept;
  OutputClaim& operator=(OutputClaim&& other) noexcept;
  ~OutputClaim();
  // Whether the folder held flatnet output of this role before (a rerun or --resume).
  bool existed() const { return existed_; }

 private:
  friend OutputClaim claim_output_folder(const std::filesystem::path&, const OutputRole&);
  void release() noexcept;
  int fd_ = -1;
  bool existed_ = false;
  // Undone when the claim ends by an exception before anything else was written: bad input
  // leaves no trace (no empty folder, no marker).
  std::filesystem::path dir_;
  bool created_dir_ = false, wrote_marker_ = false;
  int exceptions_at_claim_ = 0;
};

// Errors name the folder and what is wrong (another role, other settings, foreign files, locked).
OutputClaim claim_output_folder(const std::filesystem::path& dir, const OutputRole& role);

// Refuses (Error naming the folder) a write to `file` inside a folder this process claimed whose
// `.flatnet-lock` is gone or is no longer the file the claim locked. A file outside every held
// folder passes. Called by write_atomically before it makes folders and again before its rename.
void require_claim_intact(const std::filesystem::path& file);

// The marker's file name, for code that lists a folder's own files.
constexpr const char* kOutputMarker = ".flatnet-output";
constexpr const char* kOutputLock = ".flatnet-lock";

}  // namespace flatnet
