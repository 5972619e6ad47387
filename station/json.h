#pragma once
// A tiny JSON object writer for the one-line `--json` summaries.
#include <string>
#include <vector>

namespace station {

class JsonObject {
 public:
  JsonObject& add(const std::string& key, const std::string& value);
  JsonObject& add(const std::string& key, const char* value) { return add(key, std::string(value)); }
  JsonObject& add(const std::string& key, double value);
  JsonObject& add(const std::string& key, long long value);
  JsonObject& add(const std::string& key, int value) { return add(key, (long long)value); }
  JsonObject& add(const std::string& key, std::size_t value) { return add(key, (long long)value); }
  JsonObject& add(const std::string& key, bool value);
  JsonObject& add(const std::string& key, const JsonObject& value);
  JsonObject& add(const std::string& key, const std::vector<double>& values);  ///< a number array
  JsonObject& add(const std::string& key, const std::vector<std::string>& values);  ///< a string array
  JsonObject& add_null(const std::string& key);
  std::string str() const;

 private:
  JsonObject& raw(const std::string& key, const std::string& json);
  std::vector<std::string> items_;
};

/// JSON string literal with escapes.
std::string json_quote(const std::string& s);

}  // namespace station
