#include "train/csv_log.hpp"

#include "core/util.hpp"

namespace flatnet {

CsvLog::CsvLog(std::filesystem::path path, const std::string& header) : path_(std::move(path)), text_(header + "\n") {
  flush();  // the file exists (with its header) from the start, as it did when it was streamed
}

void CsvLog::flush() const { write_text_atomically(path_, text_); }

}  // namespace flatnet
