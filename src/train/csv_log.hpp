#pragma once
// A trainer's CSV log (log.csv, val.csv). Rows are kept in memory and the whole file is rewritten
// atomically by flush() (core/util write_text_atomically): a reader, a full disk or a killed run
// never leaves a half-written row, and a failed write is an Error naming the file. Trainers flush
// when they add a row the user should see now (a log line, a validation) and at the end; their
// logs are a few hundred rows.
#include <cstdint>
#include <filesystem>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

namespace flatnet {

class CsvLog {
 public:
  // A fresh log: the file is written now, holding the header.
  CsvLog(std::filesystem::path path, const std::string& header);
  // A resumed run's log: the rows of `path` up to `last_step` (their first field; rows past the
  // checkpoint are the ones the resumed run repeats), under `header` (an older flatnet's log
  // gets the current header; its rows keep their fewer fields). Rows that do not start with a
  // step (a line cut short, an edit) are dropped with a warning on stderr: the checkpoint, not
  // the log, is the run's state. A missing file starts a fresh log.
  static CsvLog resume(std::filesystem::path path, const std::string& header, int64_t last_step);

  // Appends one row; the values are joined with commas.
  template <typename... Values>
  void add(const Values&... values) {
    std::ostringstream row;
    const char* sep = "";
    ((row << sep << values, sep = ","), ...);
    text_ += row.str() + "\n";
  }
  void flush() const;
  // (step, value) of the rows whose first field and field `index` are numbers (a resumed run's
  // curves from the rows it kept).
  std::vector<std::pair<double, double>> column(size_t index) const;
  const std::filesystem::path& path() const { return path_; }

 private:
  CsvLog(std::filesystem::path path, std::string text, bool) : path_(std::move(path)), text_(std::move(text)) {}
  std::filesystem::path path_;
  std::string text_;
};

}  // namespace flatnet
