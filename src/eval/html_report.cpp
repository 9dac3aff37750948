#include "eval/html_report.hpp"

#include <map>
#include <set>
#include <sstream>

#include <opencv2/imgcodecs.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/tables.hpp"
#include "io/image.hpp"

namespace flatnet {

namespace {

std::string base64(const std::vector<unsigned char>& bytes) {
  static const char* digits = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  for (size_t i = 0; i < bytes.size(); i += 3) {
    const uint32_t n = (uint32_t(bytes[i]) << 16) | (i + 1 < bytes.size() ? uint32_t(bytes[i + 1]) << 8 : 0) |
                       (i + 2 < bytes.size() ? uint32_t(bytes[i + 2]) : 0);
    out += digits[(n >> 18) & 63];
    out += digits[(n >> 12) & 63];
    out += i + 1 < bytes.size() ? digits[(n >> 6) & 63] : '=';
    out += i + 2 < bytes.size() ? digits[n & 63] : '=';
  }
  return out;
}

// An image file as a JPEG data URI (quality 90), at most `size` pixels on its longer side.
std::string jpeg_data_uri(const std::filesystem::path& file, int64_t size) {
  auto rgb = read_rgb(file);  // {3,H,W} in [0,1]
  const int64_t h = rgb.size(1), w = rgb.size(2), longer = std::max(h, w);
  if (longer > size)
    rgb = resize(rgb, std::max<int64_t>(1, h * size / longer), std::max<int64_t>(1, w * size / longer));
  const auto bgr = (rgb.flip(0).permute({1, 2, 0}).clamp(0, 1) * 255).round().to(torch::kUInt8).contiguous();
  const cv::Mat mat(int(bgr.size(0)), int(bgr.size(1)), CV_8UC3, bgr.data_ptr<uint8_t>());
  std::vector<unsigned char> jpeg;
  require(cv::imencode(".jpg", mat, jpeg, {cv::IMWRITE_JPEG_QUALITY, 90}), file, "could not be encoded as JPEG");
  return "data:image/jpeg;base64," + base64(jpeg);
}

// A table cell whose sort key is the number (empty for NaN: sorted last).
std::string number_cell(double value, const std::string& shown) {
  std::ostringstream o;
  o << "<td data-v=\"";
  if (std::isfinite(value)) o << value;
  o << "\">" << html_escape(shown) << "</td>";
  return o.str();
}

std::string id_of(const std::string& text) {
  std::string id;
  for (const char c : text) id += std::isalnum(static_cast<unsigned char>(c)) ? c : '_';
  return id;
}

const char* kStyle = R"(
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px}h2{font-size:18px;margin-top:36px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:8px 0}td,th{padding:3px 8px;border-bottom:1px solid #e4e4e4;text-align:right}
td:first-child,th:first-child{text-align:left}th{background:#f3f3f3;position:sticky;top:0}
table.sortable th{cursor:pointer;user-select:none}table.sortable th[data-dir=asc]::after{content:" \25B2"}
table.sortable th[data-dir=desc]::after{content:" \25BC"}
.gallery td{text-align:center;vertical-align:top;font-size:12px}.gallery img{width:128px;height:128px;cursor:pointer;display:block}
.compare{display:flex;gap:16px;align-items:flex-start;margin:12px 0}
.stage{position:relative;width:384px;height:384px;background:#000}.stage img{position:absolute;left:0;top:0;width:384px;height:384px;image-rendering:auto}
.stage .split{position:absolute;top:0;bottom:0;width:2px;background:#ff0;pointer-events:none}
.controls label{display:block;margin:6px 0}.controls input[type=range]{width:384px}
.scroll{max-height:420px;overflow:auto;display:inline-block}p.note{color:#555}
)";

// Sorting by header click; the comparison's two pictures from the gallery's; `ready` for tests.
const char* kScript = R"(
function sortBy(th){
  const table=th.closest('table'), tbody=table.tBodies[0], col=[...th.parentNode.children].indexOf(th);
  const dir=th.dataset.dir==='asc'?'desc':'asc';
  for(const h of th.parentNode.children) delete h.dataset.dir;
  th.dataset.dir=dir;
  const key=r=>{const c=r.cells[col];const v=c.dataset.v!==undefined?c.dataset.v:c.textContent;
    const n=parseFloat(v);return v===''?null:(isNaN(n)?v:n);};
  const rows=[...tbody.rows];
  rows.sort((a,b)=>{const x=key(a),y=key(b);if(x===null)return 1;if(y===null)return -1;
    const c=(typeof x==='number'&&typeof y==='number')?x-y:String(x).localeCompare(String(y));
    return dir==='asc'?c:-c;});
  for(const r of rows) tbody.appendChild(r);
}
for(const th of document.querySelectorAll('table.sortable th')) th.addEventListener('click',()=>sortBy(th));
function picture(set,image,method){
  const img=document.querySelector('img[data-set="'+set+'"][data-image="'+CSS.escape(image)+'"][data-method="'+CSS.escape(method)+'"]');
  return img?img.src:'';
}
for(const box of document.querySelectorAll('.compare')){
  const set=box.dataset.set, q=s=>box.querySelector(s);
  const update=()=>{
    q('img.left').src=picture(set,q('select.image').value,q('select.a').value);
    q('img.right').src=picture(set,q('select.image').value,q('select.b').value);
    const v=q('input.slider').value;
    q('img.left').style.clipPath='inset(0 '+(100-v)+'% 0 0)';
    q('.split').style.left=v+'%';
  };
  for(const c of box.querySelectorAll('select,input')) c.addEventListener('input',update);
  for(const img of document.querySelectorAll('img[data-set="'+set+'"]')) img.addEventListener('click',()=>{
    q('select.image').value=img.dataset.image;
    if(img.dataset.method!=='ground truth') q('select.b').value=img.dataset.method;
    update();box.scrollIntoView({behavior:'smooth'});});
  update();
}
document.body.dataset.ready='yes';
)";

void summary_table(std::ostringstream& h, const HtmlSet& set) {
  bool lpips = false;
  for (const auto& s : set.scores) lpips = lpips || std::isfinite(s.lpips);
  h << "<table class=\"sortable\"><thead><tr><th>method</th><th>images</th><th>PSNR dB</th><th>SSIM</th><th>NIQE</th>"
    << (lpips ? "<th>LPIPS</th>" : "")
    << "<th>colour kept</th><th>detail kept</th><th>brightness</th><th>ms per image</th></tr></thead><tbody>\n";
  for (size_t i = 0; i < set.scores.size(); ++i) {
    const auto& s = set.scores[i];
    const double ms = i < set.ms_per_image.size() ? set.ms_per_image[i] : std::nan("");
    h << "<tr><td>" << html_escape(s.method) << "</td>" << number_cell(double(s.count), std::to_string(s.count))
      << number_cell(s.psnr, plus_minus(s.psnr, s.psnr_sd, 2)) << number_cell(s.ssim, plus_minus(s.ssim, s.ssim_sd, 3))
      << number_cell(s.niqe, plus_minus(s.niqe, s.niqe_sd, 2));
    if (lpips) h << number_cell(s.lpips, plus_minus(s.lpips, s.lpips_sd, 3));
    h << number_cell(s.colour_kept, fixed(s.colour_kept, 2)) << number_cell(s.detail_kept, fixed(s.detail_kept, 2))
      << number_cell(s.brightness, fixed(s.brightness, 2)) << number_cell(ms, fixed(ms, 1)) << "</tr>\n";
  }
  h << "</tbody></table>\n";
}

// The first `gallery` images that every method has, with the truth's file for each.
std::vector<std::pair<std::string, std::filesystem::path>> gallery_images(const HtmlSet& set) {
  std::map<std::string, std::filesystem::path> truth;
  for (const auto& p : list_images(set.gt_dir, kImageExtensions)) truth[p.stem().string() + ".png"] = p;
  std::map<std::string, size_t> methods_per_image;
  std::vector<std::string> order;
  for (const auto& s : set.images) {
    if (methods_per_image[s.image]++ == 0) order.push_back(s.image);
  }
  std::vector<std::pair<std::string, std::filesystem::path>> out;
  for (const auto& image : order) {
    if (static_cast<int>(out.size()) >= set.gallery) break;
    if (methods_per_image[image] == set.methods.size() && truth.count(image)) out.emplace_back(image, truth[image]);
  }
  return out;
}

void gallery(std::ostringstream& h, const HtmlSet& set,
             const std::vector<std::pair<std::string, std::filesystem::path>>& images) {
  std::map<std::pair<std::string, std::string>, const ImageScore*> score;
  for (const auto& s : set.images) score[{s.image, s.method}] = &s;
  const auto sid = html_escape(id_of(set.name));
  h << "<table class=\"gallery\"><thead><tr><th>scene</th><th>ground truth</th>";
  for (const auto& m : set.methods) h << "<th>" << html_escape(m) << "</th>";
  h << "</tr></thead><tbody>\n";
  for (const auto& [image, truth] : images) {
    const auto name = html_escape(image);
    h << "<tr><td>" << name << "</td><td><img alt=\"truth\" data-set=\"" << sid << "\" data-image=\"" << name
      << "\" data-method=\"ground truth\" src=\"" << jpeg_data_uri(truth, 256) << "\"></td>";
    for (const auto& m : set.methods) {
      const auto* s = score.at({image, m});
      h << "<td><img alt=\"" << html_escape(m) << "\" data-set=\"" << sid << "\" data-image=\"" << name
        << "\" data-method=\"" << html_escape(m) << "\" src=\"" << jpeg_data_uri(set.rec_dir / m / image, 256) << "\">"
        << fixed(s->psnr, 2) << " dB, " << fixed(s->ssim, 3) << "</td>";
    }
    h << "</tr>\n";
  }
  h << "</tbody></table>\n";
}

void comparison(std::ostringstream& h, const HtmlSet& set,
                const std::vector<std::pair<std::string, std::filesystem::path>>& images) {
  auto options = [&](const std::string& selected) {
    std::string o = "<option>ground truth</option>";
    for (const auto& m : set.methods)
      o += "<option" + std::string(m == selected ? " selected" : "") + ">" + html_escape(m) + "</option>";
    return o;
  };
  h << "<div class=\"compare\" data-set=\"" << html_escape(id_of(set.name)) << "\"><div class=\"stage\">"
    << "<img class=\"right\" alt=\"right\"><img class=\"left\" alt=\"left\"><div class=\"split\"></div></div>"
    << "<div class=\"controls\"><label>scene <select class=\"image\">";
  for (const auto& [image, truth] : images) h << "<option>" << html_escape(image) << "</option>";
  h << "</select></label><label>left <select class=\"a\">" << options("") << "</select></label>"
    << "<label>right <select class=\"b\">" << options(set.methods.empty() ? "" : set.methods.back())
    << "</select></label><label><input class=\"slider\" type=\"range\" min=\"0\" max=\"100\" value=\"50\"></label>"
    << "<p class=\"note\">Drag the slider to move the split; click a picture in the gallery to show it on the "
       "right.</p></div></div>\n";
}

void per_image_table(std::ostringstream& h, const HtmlSet& set) {
  bool lpips = false;
  for (const auto& s : set.images) lpips = lpips || std::isfinite(s.lpips);
  std::map<std::pair<std::string, std::string>, const ImageScore*> score;
  std::vector<std::string> order;
  for (const auto& s : set.images) {
    if (score.emplace(std::make_pair(s.image, s.method), &s).second &&
        (order.empty() || std::find(order.begin(), order.end(), s.image) == order.end()))
      order.push_back(s.image);
  }
  h << "<div class=\"scroll\"><table class=\"sortable\"><thead><tr><th>image</th>";
  for (const auto& m : set.methods)
    h << "<th>" << html_escape(m) << " PSNR</th><th>" << html_escape(m) << " SSIM</th>"
      << (lpips ? "<th>" + html_escape(m) + " LPIPS</th>" : "");
  h << "</tr></thead><tbody>\n";
  for (const auto& image : order) {
    h << "<tr><td>" << html_escape(image) << "</td>";
    for (const auto& m : set.methods) {
      const auto it = score.find({image, m});
      const double p = it == score.end() ? std::nan("") : it->second->psnr;
      const double s = it == score.end() ? std::nan("") : it->second->ssim;
      const double l = it == score.end() ? std::nan("") : it->second->lpips;
      h << number_cell(p, fixed(p, 2)) << number_cell(s, fixed(s, 3));
      if (lpips) h << number_cell(l, fixed(l, 3));
    }
    h << "</tr>\n";
  }
  h << "</tbody></table></div>\n";
}

}  // namespace

std::string html_escape(const std::string& text) {
  std::string out;
  for (const char c : text) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      case '\'':
        out += "&#39;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

std::string html_report(const std::string& title, const std::string& intro, const std::vector<HtmlSet>& sets) {
  std::ostringstream h;
  h << "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
    << "<meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; img-src data:; "
       "style-src 'unsafe-inline'; script-src 'unsafe-inline'\">"
    << "<title>" << html_escape(title) << "</title><style>" << kStyle << "</style></head><body>\n<h1>"
    << html_escape(title) << "</h1>\n<p class=\"note\">" << html_escape(intro) << "</p>\n";
  for (const auto& set : sets) {
    const auto images = gallery_images(set);
    h << "<h2 id=\"" << html_escape(id_of(set.name)) << "\">" << html_escape(set.name) << "</h2>\n<p class=\"note\">"
      << html_escape(set.caption) << " Click a column's heading to sort by it.</p>\n";
    summary_table(h, set);
    if (!images.empty()) {
      h << "<h3>Compare two methods</h3>\n";
      comparison(h, set, images);
      h << "<h3>The first " << images.size() << " scenes</h3>\n";
      gallery(h, set, images);
    }
    h << "<h3>Every image</h3>\n";
    per_image_table(h, set);
  }
  h << "<script>" << kScript << "</script>\n</body></html>\n";
  return h.str();
}

}  // namespace flatnet
