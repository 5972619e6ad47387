#pragma once
// Devices are named by URI, "scheme:path?key=value&key=value", and made by a
// registry of factories keyed by scheme. `station devices` lists the registry.
// Back-ends register explicitly (register_*_devices functions), never through
// static initialisers, which static linking drops.
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "drivers/scanner.h"

namespace station {

/// A parsed device URI: "sim:synthetic?noise=0.001" -> scheme "sim",
/// path "synthetic", options {noise: 0.001}. Values are percent-decoded.
struct DeviceUri {
  std::string text;
  std::string scheme;
  std::string path;
  DeviceOptions options;
};
/// DeviceError when the text has no "scheme:" part.
DeviceUri parse_device_uri(const std::string& text);

/// Shared state handed to every factory of one registry. Simulated devices
/// use it to put a scanner and a turntable on the same virtual bench.
struct DeviceContext {
  std::map<std::string, std::shared_ptr<void>> shared;
};

enum class DeviceKind { kScanner, kTurntable };

struct DeviceInfo {
  std::string uri;          ///< example or detected URI
  DeviceKind kind;
  std::string description;
  bool available = true;    ///< false when detected but not usable (no permission...)
};

class DeviceRegistry {
 public:
  using ScannerFactory =
      std::function<std::unique_ptr<Scanner>(const DeviceUri&, DeviceContext&)>;
  using TurntableFactory =
      std::function<std::unique_ptr<Turntable>(const DeviceUri&, DeviceContext&)>;
  /// Lists the concrete devices of one back-end (probing hardware if it must).
  using Lister = std::function<std::vector<DeviceInfo>()>;

  /// `prefix` is "scheme:path" or just "scheme:" (matches any path).
  void add_scanner(const std::string& prefix, ScannerFactory factory, Lister lister);
  void add_turntable(const std::string& prefix, TurntableFactory factory, Lister lister);

  /// DeviceError("URI: unknown device ...") when nothing matches.
  std::unique_ptr<Scanner> make_scanner(const std::string& uri);
  std::unique_ptr<Turntable> make_turntable(const std::string& uri);
  std::vector<DeviceInfo> list() const;
  DeviceContext& context() { return context_; }

 private:
  struct Entry {
    std::string prefix;
    ScannerFactory scanner;
    TurntableFactory turntable;
    Lister lister;
  };
  const Entry* find(const DeviceUri& uri, DeviceKind kind) const;
  /// "URI: unknown scanner (supported: ...; attached now: ...; see `station devices`)".
  std::string unknown(const std::string& text, DeviceKind kind) const;
  std::vector<Entry> entries_;
  DeviceContext context_;
};

}  // namespace station
