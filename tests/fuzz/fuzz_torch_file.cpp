// A PyTorch file (torch.save zip or legacy archive, pickle protocol 2): the zip directory, the
// pickle machine, the storages, and the tensors it names.
#include "fuzz_common.hpp"
#include "io/torch_file.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "weights.pt");
  flatnet::fuzz::expect_clean([&] {
    const auto root = flatnet::read_torch_file(path);
    (void)flatnet::tensors_in(*root);
  });
  return 0;
}
