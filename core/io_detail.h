#pragma once
// Private helpers shared by the format readers in core/*_io.cpp. Not part of the
// public interface: include core/io.h instead.
#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <string_view>

#include "core/error.h"

namespace station::io_detail {

/// Throws FormatError("NAME: problem").
[[noreturn]] inline void format_error(const std::string& name, const std::string& problem) {
  throw FormatError(name + ": " + problem);
}

/// The largest coordinate magnitude a reader accepts. Scans are in metres or
/// millimetres; past 1e9 (a million kilometres in millimetres) a value is a corrupt
/// file or wrong units, and squared distances near float's range overflow later
/// stages (a 1e38 coordinate made h = 1.4e38 and an internal winding-number error).
inline constexpr double kMaxCoordinate = 1e9;

/// Refuses an input that exists and is neither a regular file nor a folder (a device:
/// /dev/zero was read until memory ran out, and opening a serial port can reset the
/// board behind it; a FIFO blocked the open), before it is opened: IoError naming it.
void refuse_special_file(const std::string& name);

/// Empty when (x, y, z) is a usable coordinate, else the problem in a few words.
inline std::string coordinate_problem(float x, float y, float z) {
  if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) return "non-finite coordinate";
  const double m = std::max({std::fabs(double(x)), std::fabs(double(y)), std::fabs(double(z))});
  if (m > kMaxCoordinate) {
    char buf[128];
    std::snprintf(buf, sizeof buf, "coordinate %.3g is beyond +-1e9 (wrong units or a corrupt file?)", m);
    return buf;
  }
  return {};
}

inline bool is_space(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f'; }

inline std::string_view trim(std::string_view s) {
  while (!s.empty() && (is_space(s.front()) || s.front() == '\n')) s.remove_prefix(1);
  while (!s.empty() && (is_space(s.back()) || s.back() == '\n')) s.remove_suffix(1);
  return s;
}

/// A short, printable rendering of a token for error messages.
inline std::string quote(std::string_view s) {
  std::string out = "'";
  for (char c : s.substr(0, 40)) out += (c >= 32 && c < 127) ? c : '?';
  if (s.size() > 40) out += "...";
  return out + "'";
}

/// Parses a whole token as a double (from_chars; "+1", "inf", "nan" accepted).
/// Overflow gives +-inf and underflow a denormal or zero, like strtod.
inline bool parse_double(std::string_view tok, double& out) {
  if (tok.size() > 1 && tok[0] == '+' && tok[1] != '-' && tok[1] != '+') tok.remove_prefix(1);
  if (tok.empty()) return false;
  const char* end = tok.data() + tok.size();
  auto [ptr, ec] = std::from_chars(tok.data(), end, out);
  if (ptr != end) return false;
  if (ec == std::errc()) return true;
  if (ec != std::errc::result_out_of_range || tok.size() > 256) return false;
  // from_chars leaves the value unset when out of range; strtod gives inf or a denormal.
  char buf[260];
  std::memcpy(buf, tok.data(), tok.size());
  buf[tok.size()] = '\0';
  char* e = nullptr;
  out = std::strtod(buf, &e);
  return e == buf + tok.size();
}

/// Parses a whole token as a signed 64-bit integer ("+5" accepted).
inline bool parse_int(std::string_view tok, long long& out) {
  if (tok.size() > 1 && tok[0] == '+' && tok[1] != '-') tok.remove_prefix(1);
  if (tok.empty()) return false;
  const char* end = tok.data() + tok.size();
  auto [ptr, ec] = std::from_chars(tok.data(), end, out);
  return ec == std::errc() && ptr == end;
}

/// Splits text into whitespace-separated tokens, counting lines (1-based).
class Tokenizer {
 public:
  Tokenizer(std::string_view text, long long first_line = 1)
      : p_(text.data()), end_(text.data() + text.size()), line_(first_line), tok_line_(first_line) {}

  /// Next token anywhere (crossing line ends); false at the end of the text.
  bool next(std::string_view& tok) {
    while (p_ < end_ && (is_space(*p_) || *p_ == '\n')) {
      if (*p_ == '\n') ++line_;
      ++p_;
    }
    if (p_ >= end_) return false;
    const char* s = p_;
    while (p_ < end_ && !is_space(*p_) && *p_ != '\n') ++p_;
    tok = std::string_view(s, static_cast<std::size_t>(p_ - s));
    tok_line_ = line_;
    return true;
  }

  /// Line of the last token returned (at the end of the text: still that line).
  long long line() const { return tok_line_; }
  std::size_t remaining() const { return static_cast<std::size_t>(end_ - p_); }

 private:
  const char* p_;
  const char* end_;
  long long line_;
  long long tok_line_;
};

/// Iterates over lines ("\n" or "\r\n"), counting them (1-based).
class LineReader {
 public:
  explicit LineReader(std::string_view text) : text_(text) {}

  bool next(std::string_view& line) {
    if (pos_ >= text_.size()) return false;
    const std::size_t nl = text_.find('\n', pos_);
    const std::size_t stop = nl == std::string_view::npos ? text_.size() : nl;
    line = text_.substr(pos_, stop - pos_);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    pos_ = nl == std::string_view::npos ? text_.size() : nl + 1;
    ++line_;
    return true;
  }

  long long line() const { return line_; }
  /// Byte offset just past the last line returned.
  std::size_t offset() const { return pos_; }
  std::size_t remaining() const { return text_.size() - pos_; }

 private:
  std::string_view text_;
  std::size_t pos_ = 0;
  long long line_ = 0;
};

/// Splits one line into at most `max` tokens; returns how many were found. The
/// count keeps growing past `max` so callers can tell a line was longer.
inline std::size_t split(std::string_view line, std::string_view* toks, std::size_t max) {
  std::size_t n = 0, i = 0;
  while (true) {
    while (i < line.size() && is_space(line[i])) ++i;
    if (i >= line.size()) break;
    const std::size_t s = i;
    while (i < line.size() && !is_space(line[i])) ++i;
    if (n < max) toks[n] = line.substr(s, i - s);
    ++n;
  }
  return n;
}

/// Converts a colour channel to 0..255: values of integer properties are taken as
/// 8-bit, floating ones as [0, 1].
inline std::uint8_t to_channel(double v, bool unit_range) {
  if (unit_range) v *= 255.0;
  if (!(v > 0)) return 0;  // also NaN
  if (v >= 255) return 255;
  return static_cast<std::uint8_t>(std::lround(v));
}

}  // namespace station::io_detail
