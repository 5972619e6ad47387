#include "station/report.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "station/render.h"

namespace station {

std::string html_escape(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    switch (c) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      case '\'': out += "&#39;"; break;
      default: out += c;
    }
  }
  return out;
}

std::string svg_bar_chart(const std::vector<double>& values, const std::vector<std::string>& labels,
                          const std::string& unit, double warn_above) {
  const int bar = 28, gap = 8, height = 160, left = 48, bottom = 24, top = 12;
  const int width = left + int(values.size()) * (bar + gap) + gap;
  double vmax = 0;
  for (double v : values)
    if (std::isfinite(v)) vmax = std::max(vmax, v);
  if (warn_above > 0) vmax = std::max(vmax, warn_above);
  if (vmax <= 0) vmax = 1;
  char buf[512];
  std::string s;
  std::snprintf(buf, sizeof buf,
                "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%d\" height=\"%d\" "
                "font-family=\"sans-serif\" font-size=\"10\">",
                width, height + bottom + top);
  s += buf;
  const int y0 = top + height;
  std::snprintf(buf, sizeof buf, "<line x1=\"%d\" y1=\"%d\" x2=\"%d\" y2=\"%d\" stroke=\"#444\"/>", left, y0,
                width, y0);
  s += buf;
  std::snprintf(buf, sizeof buf, "<text x=\"2\" y=\"%d\">%.3g %s</text><text x=\"2\" y=\"%d\">0</text>",
                top + 8, vmax, html_escape(unit).c_str(), y0);
  s += buf;
  if (warn_above > 0) {
    const int wy = y0 - int(std::lround(height * warn_above / vmax));
    std::snprintf(buf, sizeof buf,
                  "<line x1=\"%d\" y1=\"%d\" x2=\"%d\" y2=\"%d\" stroke=\"#c00\" stroke-dasharray=\"4 3\"/>",
                  left, wy, width, wy);
    s += buf;
  }
  for (std::size_t i = 0; i < values.size(); ++i) {
    const double v = std::isfinite(values[i]) ? std::max(0.0, values[i]) : 0.0;
    const int h = int(std::lround(height * v / vmax));
    const int x = left + gap + int(i) * (bar + gap);
    const bool warn = (warn_above > 0 && v > warn_above) || !std::isfinite(values[i]);
    std::snprintf(buf, sizeof buf,
                  "<rect x=\"%d\" y=\"%d\" width=\"%d\" height=\"%d\" fill=\"%s\"><title>%s: %.4g %s</title></rect>",
                  x, y0 - h, bar, h, warn ? "#d33" : "#4a7bd0",
                  html_escape(i < labels.size() ? labels[i] : std::to_string(i)).c_str(), values[i],
                  html_escape(unit).c_str());
    s += buf;
    std::snprintf(buf, sizeof buf, "<text x=\"%d\" y=\"%d\" text-anchor=\"middle\">%s</text>", x + bar / 2,
                  y0 + 14, html_escape(i < labels.size() ? labels[i] : std::to_string(i)).c_str());
    s += buf;
  }
  s += "</svg>";
  return s;
}

std::string report_html(const std::string& title, const std::vector<ReportSection>& sections) {
  std::string h;
  h += "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n<title>" + html_escape(title) +
       "</title>\n<style>\n"
       "body{font-family:sans-serif;margin:24px;color:#222;max-width:1400px}\n"
       "h1{font-size:22px}h2{font-size:18px;border-bottom:1px solid #ccc;padding-bottom:4px;margin-top:28px}\n"
       "table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;padding:3px 8px;"
       "text-align:right}th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}\n"
       "figure{display:inline-block;margin:6px;text-align:center}figcaption{font-size:12px;color:#555}\n"
       "img{border:1px solid #ddd}\n</style></head><body>\n";
  h += "<h1>" + html_escape(title) + "</h1>\n";
  for (const ReportSection& s : sections) {
    h += "<h2>" + html_escape(s.title) + "</h2>\n";
    if (!s.text.empty()) h += "<p>" + html_escape(s.text) + "</p>\n";
    for (const ReportTable& t : s.tables) {
      h += "<table><tr>";
      for (const std::string& c : t.header) h += "<th>" + html_escape(c) + "</th>";
      h += "</tr>\n";
      for (const auto& row : t.rows) {
        h += "<tr>";
        for (const std::string& c : row) h += "<td>" + html_escape(c) + "</td>";
        h += "</tr>\n";
      }
      h += "</table>\n";
    }
    if (!s.svg.empty()) h += "<div>" + s.svg + "</div>\n";
    for (const ReportFigure& f : s.figures)
      h += "<figure><img alt=\"" + html_escape(f.caption) + "\" src=\"data:image/png;base64," + base64(f.png) +
           "\"><figcaption>" + html_escape(f.caption) + "</figcaption></figure>\n";
  }
  h += "</body></html>\n";
  return h;
}

}  // namespace station
