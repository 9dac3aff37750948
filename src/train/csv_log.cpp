#include "train/csv_log.hpp"

#include <algorithm>
#include <fstream>
#include <iostream>

#include "core/util.hpp"

namespace flatnet {

CsvLog::CsvLog(std::filesystem::path path, const std::string& header) : path_(std::move(path)), text_(header + "\n") {
  flush();  // the file exists (with its header) from the start
}

namespace {
std::ptrdiff_t columns(const std::string& row) { return std::count(row.begin(), row.end(), ',') + 1; }
}  // namespace

CsvLog CsvLog::resume(std::filesystem::path path, const std::string& header, int64_t last_step) {
  if (!std::filesystem::exists(path)) return CsvLog(std::move(path), header);
  std::ifstream in(path);
  std::string line, kept = header + "\n";
  bool first_line = true;
  int64_t line_number = 0, dropped = 0, first_dropped = 0;
  while (std::getline(in, line)) {
    ++line_number;
    if (first_line) {  // the old header gives way to the current one
      first_line = false;
      continue;
    }
    const auto field = line.substr(0, line.find(','));
    size_t used = 0;
    int64_t step = -1;
    try {
      step = std::stoll(field, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    if (used == 0 || used != field.size() || step < 0) {
      if (dropped++ == 0) first_dropped = line_number;
      continue;
    }
    if (step > last_step) continue;
    // A row from before the header gained columns (a run resumed by a newer flatnet): the new columns
    // empty, not recorded, so that every row has the header's columns.
    for (auto n = columns(line); n < columns(header); ++n) line += ",";
    kept += line + "\n";
  }
  if (dropped > 0)
    std::cerr << path.string() << ": dropped " << dropped << " malformed row(s) (the first at line " << first_dropped
              << "); training state comes from the checkpoint\n";
  CsvLog log(std::move(path), std::move(kept), true);
  log.flush();
  return log;
}

void CsvLog::flush() const { write_text_atomically(path_, text_); }

std::vector<std::pair<double, double>> CsvLog::column(size_t column) const {
  std::vector<std::pair<double, double>> out;
  std::istringstream in(text_);
  std::string line;
  std::getline(in, line);  // the header
  while (std::getline(in, line)) {
    std::vector<std::string> fields;
    std::stringstream ss(line);
    for (std::string f; std::getline(ss, f, ',');) fields.push_back(f);
    if (fields.size() <= column || !is_decimal_number(fields[0]) || !is_decimal_number(fields[column])) continue;
    out.emplace_back(std::strtod(fields[0].c_str(), nullptr), std::strtod(fields[column].c_str(), nullptr));
  }
  return out;
}

}  // namespace flatnet
