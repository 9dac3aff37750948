#include "io/dataset.hpp"

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

DatasetLists split_lists(const std::filesystem::path& dir, const std::string& split) {
  require(std::filesystem::is_directory(dir), dir, "dataset folder not found");
  return {dir / (split + "_meas.txt"), dir / (split + "_gt.txt"), dir};
}

namespace {

// A list's line names a file that exists; what is wrong names the list and the line (a name the file
// system refuses, such as one over its length limit, is the list's fault as a missing file is).
void require_listed_file(const std::filesystem::path& file, const std::filesystem::path& list, size_t line) {
  std::error_code ec;
  const bool found = std::filesystem::exists(file, ec);
  require(found && !ec, list,
          "line " + std::to_string(line) + ": " + (ec ? ec.message() + ": " : std::string("no such file ")) +
              file.string());
}

}  // namespace

std::vector<Pair> read_pairs(const DatasetLists& lists) {
  const auto meas = read_lines(lists.meas_list);
  const auto gt = read_lines(lists.gt_list);
  require(!meas.empty(), lists.meas_list, "list is empty");
  require(meas.size() == gt.size(), lists.meas_list,
          "has " + std::to_string(meas.size()) + " entries but " + lists.gt_list.string() + " has " +
              std::to_string(gt.size()) + " (the lists must pair line by line)");
  const auto root = lists.root.empty() ? lists.meas_list.parent_path() : lists.root;
  std::vector<Pair> pairs;
  pairs.reserve(meas.size());
  for (size_t i = 0; i < meas.size(); ++i) {
    Pair p{root / meas[i], root / gt[i]};
    require_listed_file(p.meas, lists.meas_list, i + 1);
    require_listed_file(p.gt, lists.gt_list, i + 1);
    pairs.push_back(std::move(p));
  }
  return pairs;
}

}  // namespace flatnet
