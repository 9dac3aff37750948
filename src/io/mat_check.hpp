#pragma once
// A check of a MATLAB v5 .mat file's own claims before matio reads it: every numeric variable's data
// holds exactly the values its dimensions say (matio would read a 500x256 header over 4 values and
// fill the rest with zeros), and what a variable claims fits in the bytes present (a 216-byte file
// declaring 20000x20000 doubles would allocate 3.2 GB). v7.3 (HDF5) files are left to HDF5.
#include <cstdint>
#include <filesystem>
#include <string>

namespace flatnet {

// The most bytes one variable may hold when its reader says nothing narrower.
inline constexpr uint64_t kMaxMatVariableBytes = 8ull << 30;

// Errors name the file, the variable and what is wrong. `bytes` is the whole file; no variable may
// hold more than `max_variable_bytes` (a compressed one is refused as it inflates past that, before
// the rest of it is inflated).
void check_mat5_sizes(const std::string& bytes, const std::filesystem::path& path,
                      uint64_t max_variable_bytes = kMaxMatVariableBytes);

}  // namespace flatnet
