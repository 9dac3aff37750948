#pragma once
// The report as one self-contained web page (`flatnet report` writes OUT/report.html beside
// report.md): per set, the methods' table (every column sortable by a click), a gallery of the
// first scenes (truth beside each method, with that image's scores), a comparison of any two
// methods (or the truth) on one scene with a slider over the split, and every image's scores in a
// sortable table. Images are embedded as JPEG data URIs and the script and style are inline: the
// page loads nothing from anywhere, opened from disk or mailed as one file.
#include <filesystem>
#include <string>
#include <vector>

#include "eval/report.hpp"

namespace flatnet {

struct HtmlSet {
  std::string name;                  // heading and the ids inside the page
  std::string caption;               // one line under the heading (plain text)
  std::vector<std::string> methods;  // in column order; reconstructions in rec_dir/<method>/<image>.png
  std::vector<MethodScore> scores;   // means, as evaluate returns them (a "ground truth" row included)
  std::vector<double> ms_per_image;  // beside `scores` (NaN where not timed)
  std::vector<ImageScore> images;    // per image and method
  std::filesystem::path gt_dir;      // the truth, by file stem
  std::filesystem::path rec_dir;
  int gallery = 8;  // scenes shown as pictures (the first ones that every method reconstructed)
};

// The page. `intro` is plain text (escaped here).
std::string html_report(const std::string& title, const std::string& intro, const std::vector<HtmlSet>& sets);

// Text made safe for HTML element content and attribute values.
std::string html_escape(const std::string& text);

}  // namespace flatnet
