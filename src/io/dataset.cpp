#include "io/dataset.hpp"

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

DatasetLists split_lists(const std::filesystem::path& dir, const std::string& split) {
  require(std::filesystem::is_directory(dir), dir, "dataset folder not found");
  return {dir / (split + "_meas.txt"), dir / (split + "_gt.txt"), dir};
}

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
    require(std::filesystem::exists(p.meas), lists.meas_list,
            "line " + std::to_string(i + 1) + ": no such file " + p.meas.string());
    require(std::filesystem::exists(p.gt), lists.gt_list,
            "line " + std::to_string(i + 1) + ": no such file " + p.gt.string());
    pairs.push_back(std::move(p));
  }
  return pairs;
}

}  // namespace flatnet
