#include "train/run_id.hpp"

#include <iomanip>
#include <random>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

std::string new_run_id() {
  std::random_device entropy;
  std::ostringstream id;
  id << std::hex << std::setfill('0') << std::setw(8) << entropy() << std::setw(8) << entropy();
  return id.str();
}

bool is_run_id(const std::string& id) {
  return id.size() == 16 && id.find_first_not_of("0123456789abcdef") == std::string::npos;
}

std::string folder_run_id(const std::filesystem::path& out) {
  const auto record = out / "run_id.txt";
  if (!std::filesystem::exists(record)) return "";
  auto id = read_file_text(record, 256);
  while (!id.empty() && (id.back() == '\n' || id.back() == '\r')) id.pop_back();
  return id;
}

void record_run_id(const std::filesystem::path& out, const std::string& id) {
  write_text_atomically(out / "run_id.txt", id + "\n");
}

void require_checkpoint_of_this_run(const std::filesystem::path& out, const std::string& checkpoint_id,
                                    const std::filesystem::path& checkpoint, const std::string& force_key) {
  const auto folder_id = folder_run_id(out);
  if (folder_id.empty()) return;  // runs from before run ids: nothing to compare
  require(checkpoint_id == folder_id, checkpoint,
          "belongs to another run (run id " + (checkpoint_id.empty() ? std::string("none") : checkpoint_id) +
              "; this folder's run is " + printable(folder_id.substr(0, 16)) +
              "); it was copied in from elsewhere? Set " + force_key + " to resume it here anyway");
}

std::string settle_run_id(const std::filesystem::path& out, bool resuming, const std::string& resumed_id,
                          const std::filesystem::path& checkpoint, bool force) {
  if (resuming && !force) require_checkpoint_of_this_run(out, resumed_id, checkpoint, "--force");
  const auto id = resuming && !resumed_id.empty() ? resumed_id : new_run_id();
  record_run_id(out, id);
  return id;
}

}  // namespace flatnet
