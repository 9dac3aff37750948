// A dataset's list files (FlatNet's train_meas.txt / train_gt.txt): the input is split at its first
// NUL into the two lists; lines name files relative to the lists' folder (data, never a way out of it
// unless the user's own list says so).
#include "fuzz_common.hpp"
#include "io/dataset.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  const auto cut = std::min(text.find('\0'), text.size());
  const std::string meas = text.substr(0, cut), gt = cut < text.size() ? text.substr(cut + 1) : "";
  const auto meas_list =
      flatnet::fuzz::as_file(reinterpret_cast<const uint8_t*>(meas.data()), meas.size(), "train_meas.txt");
  const auto gt_list = flatnet::fuzz::as_file(reinterpret_cast<const uint8_t*>(gt.data()), gt.size(), "train_gt.txt");
  flatnet::fuzz::expect_clean([&] { (void)flatnet::read_pairs({meas_list, gt_list, meas_list.parent_path()}); });
  return 0;
}
