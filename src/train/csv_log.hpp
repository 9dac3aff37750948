#pragma once
// A trainer's CSV log (log.csv, val.csv). Rows are kept in memory and the whole file is rewritten
// atomically by flush() (core/util write_text_atomically): a reader, a full disk or a killed run
// never leaves a half-written row, and a failed write is an Error naming the file. The mask and
// code-pair trainers flush at each validation and at the end; their logs are a few hundred rows.
#include <filesystem>
#include <sstream>
#include <string>

namespace flatnet {

class CsvLog {
 public:
  CsvLog(std::filesystem::path path, const std::string& header);
  // Appends one row; the values are joined with commas.
  template <typename... Values>
  void add(const Values&... values) {
    std::ostringstream row;
    const char* sep = "";
    ((row << sep << values, sep = ","), ...);
    text_ += row.str() + "\n";
  }
  void flush() const;
  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
  std::string text_;
};

}  // namespace flatnet
