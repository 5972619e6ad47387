#include "station/json.h"

#include <cmath>
#include <cstdio>

namespace station {

std::string json_quote(const std::string& s) {
  std::string out = "\"";
  for (unsigned char c : s) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\t': out += "\\t"; break;
      case '\r': out += "\\r"; break;
      default:
        if (c < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof buf, "\\u%04x", c);
          out += buf;
        } else {
          out += char(c);
        }
    }
  }
  return out + "\"";
}

JsonObject& JsonObject::raw(const std::string& key, const std::string& json) {
  items_.push_back(json_quote(key) + ":" + json);
  return *this;
}
JsonObject& JsonObject::add(const std::string& key, const std::string& v) { return raw(key, json_quote(v)); }
JsonObject& JsonObject::add(const std::string& key, double v) {
  if (!std::isfinite(v)) return raw(key, "null");
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.6g", v);
  return raw(key, buf);
}
JsonObject& JsonObject::add(const std::string& key, long long v) { return raw(key, std::to_string(v)); }
JsonObject& JsonObject::add(const std::string& key, bool v) { return raw(key, v ? "true" : "false"); }
JsonObject& JsonObject::add(const std::string& key, const JsonObject& v) { return raw(key, v.str()); }
JsonObject& JsonObject::add(const std::string& key, const std::vector<double>& values) {
  std::string s = "[";
  for (std::size_t i = 0; i < values.size(); ++i) {
    char buf[32];
    if (std::isfinite(values[i])) std::snprintf(buf, sizeof buf, "%.9g", values[i]);
    else std::snprintf(buf, sizeof buf, "null");
    s += (i ? "," : "") + std::string(buf);
  }
  return raw(key, s + "]");
}
JsonObject& JsonObject::add(const std::string& key, const std::vector<std::string>& values) {
  std::string s = "[";
  for (std::size_t i = 0; i < values.size(); ++i) s += (i ? "," : "") + json_quote(values[i]);
  return raw(key, s + "]");
}
JsonObject& JsonObject::add_null(const std::string& key) { return raw(key, "null"); }

std::string JsonObject::str() const {
  std::string s = "{";
  for (std::size_t i = 0; i < items_.size(); ++i) s += (i ? "," : "") + items_[i];
  return s + "}";
}

}  // namespace station
