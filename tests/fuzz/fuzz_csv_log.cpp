// A run's log.csv / val.csv, read back when a run resumes: rows kept up to the checkpoint's step,
// and a column of numbers taken from them.
#include "fuzz_common.hpp"
#include "train/csv_log.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "val.csv");
  flatnet::fuzz::expect_clean([&] {
    const auto log = flatnet::CsvLog::resume(path, "step,psnr,ssim,seconds", 1000);
    (void)log.column(1);
  });
  return 0;
}
