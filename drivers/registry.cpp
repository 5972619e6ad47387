#include "drivers/registry.h"

#include <cctype>

#include "core/error.h"

namespace station {
namespace {

std::string percent_decode(const std::string& s, const std::string& uri) {
  std::string out;
  out.reserve(s.size());
  for (std::size_t i = 0; i < s.size(); ++i) {
    if (s[i] == '%') {
      if (i + 2 >= s.size() || !std::isxdigit(static_cast<unsigned char>(s[i + 1])) ||
          !std::isxdigit(static_cast<unsigned char>(s[i + 2])))
        throw DeviceError(uri + ": bad percent escape in device URI");
      out.push_back(static_cast<char>(std::stoi(s.substr(i + 1, 2), nullptr, 16)));
      i += 2;
    } else {
      out.push_back(s[i]);
    }
  }
  return out;
}

bool matches(const std::string& prefix, const DeviceUri& uri) {
  const std::string head = uri.scheme + ":" + uri.path;
  if (!prefix.empty() && prefix.back() == ':') return prefix == uri.scheme + ":";
  return prefix == head;
}

}  // namespace

DeviceUri parse_device_uri(const std::string& text) {
  DeviceUri uri;
  uri.text = text;
  const auto colon = text.find(':');
  if (colon == std::string::npos || colon == 0)
    throw DeviceError(text + ": not a device URI (expected scheme:path, e.g. sim:synthetic)");
  uri.scheme = text.substr(0, colon);
  std::string rest = text.substr(colon + 1);
  const auto q = rest.find('?');
  uri.path = percent_decode(rest.substr(0, q), text);
  if (q != std::string::npos) {
    std::string query = rest.substr(q + 1);
    std::size_t start = 0;
    while (start <= query.size()) {
      std::size_t amp = query.find('&', start);
      if (amp == std::string::npos) amp = query.size();
      std::string item = query.substr(start, amp - start);
      if (!item.empty()) {
        const auto eq = item.find('=');
        std::string key = percent_decode(item.substr(0, eq), text);
        std::string value = eq == std::string::npos ? "1" : percent_decode(item.substr(eq + 1), text);
        if (key.empty()) throw DeviceError(text + ": empty option name in device URI");
        uri.options[key] = value;
      }
      start = amp + 1;
    }
  }
  return uri;
}

void DeviceRegistry::add_scanner(const std::string& prefix, ScannerFactory factory,
                                 Lister lister) {
  entries_.push_back({prefix, std::move(factory), nullptr, std::move(lister)});
}

void DeviceRegistry::add_turntable(const std::string& prefix, TurntableFactory factory,
                                   Lister lister) {
  entries_.push_back({prefix, nullptr, std::move(factory), std::move(lister)});
}

const DeviceRegistry::Entry* DeviceRegistry::find(const DeviceUri& uri, DeviceKind kind) const {
  // Exact "scheme:path" entries win over scheme-wide ones.
  const Entry* wide = nullptr;
  for (const Entry& e : entries_) {
    const bool right_kind = kind == DeviceKind::kScanner ? bool(e.scanner) : bool(e.turntable);
    if (!right_kind || !matches(e.prefix, uri)) continue;
    if (e.prefix.back() != ':') return &e;
    if (!wide) wide = &e;
  }
  return wide;
}

std::string DeviceRegistry::unknown(const std::string& text, DeviceKind kind) const {
  // The URI forms this build can open (a scheme-wide entry as "scheme:...") and the
  // devices attached now: a user who typed serial:/dev/ttyUSB0 learns of horus:.
  std::string supported, attached;
  for (const Entry& e : entries_) {
    if (kind == DeviceKind::kScanner ? !e.scanner : !e.turntable) continue;
    const std::string form = e.prefix.back() == ':' ? e.prefix + "..." : e.prefix;
    if (supported.find(form) == std::string::npos)
      supported += (supported.empty() ? "" : ", ") + form;
  }
  for (const DeviceInfo& i : list())
    if (i.kind == kind) attached += (attached.empty() ? "" : ", ") + i.uri;
  return text + ": unknown " + (kind == DeviceKind::kScanner ? "scanner" : "turntable") +
         " (supported: " + (supported.empty() ? "none" : supported) +
         "; attached now: " + (attached.empty() ? "none" : attached) + "; see `station devices`)";
}

std::unique_ptr<Scanner> DeviceRegistry::make_scanner(const std::string& text) {
  DeviceUri uri = parse_device_uri(text);
  const Entry* e = find(uri, DeviceKind::kScanner);
  if (!e) throw DeviceError(unknown(text, DeviceKind::kScanner));
  return e->scanner(uri, context_);
}

std::unique_ptr<Turntable> DeviceRegistry::make_turntable(const std::string& text) {
  DeviceUri uri = parse_device_uri(text);
  const Entry* e = find(uri, DeviceKind::kTurntable);
  if (!e) throw DeviceError(unknown(text, DeviceKind::kTurntable));
  return e->turntable(uri, context_);
}

std::vector<DeviceInfo> DeviceRegistry::list() const {
  std::vector<DeviceInfo> all;
  for (const Entry& e : entries_) {
    if (!e.lister) continue;
    auto infos = e.lister();
    all.insert(all.end(), infos.begin(), infos.end());
  }
  return all;
}

}  // namespace station
