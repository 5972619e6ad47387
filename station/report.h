#pragma once
// The run report: one self-contained HTML file (pictures as data: URIs, inline
// CSS and SVG, no scripts, no network).
#include <string>
#include <utility>
#include <vector>

namespace station {

struct ReportFigure {
  std::string caption;
  std::string png;  ///< PNG bytes (station/render.h encode_png)
};

struct ReportTable {
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
};

struct ReportSection {
  std::string title;
  std::string text;                    ///< a paragraph (escaped)
  std::vector<ReportTable> tables;
  std::vector<ReportFigure> figures;
  std::string svg;                     ///< inline SVG (already markup), may be empty
};

/// The whole page. Texts are HTML-escaped; figures become <img src="data:image/png;base64,...">.
std::string report_html(const std::string& title, const std::vector<ReportSection>& sections);

/// A bar chart as inline SVG: one bar per value, labelled by `labels`, with the
/// axis unit in `unit`; bars above `warn_above` (when > 0) are drawn in red.
std::string svg_bar_chart(const std::vector<double>& values, const std::vector<std::string>& labels,
                          const std::string& unit, double warn_above = 0);

std::string html_escape(const std::string& text);

}  // namespace station
