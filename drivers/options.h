#pragma once
// Readers of device options (the `options` of a profile's scanner or turntable,
// merged into its URI's query), shared by every driver.
#include <set>
#include <string>

#include "drivers/scanner.h"

namespace station {

/// Option readers: DeviceError "URI: option KEY=VALUE: problem" on bad values.
double option_number(const DeviceOptions& options, const std::string& key, double fallback,
                     double min, double max, const std::string& uri);
int option_integer(const DeviceOptions& options, const std::string& key, int fallback, int min,
                   int max, const std::string& uri);
/// DeviceError naming the first key not in `known`.
void reject_unknown_options(const DeviceOptions& options, const std::set<std::string>& known,
                            const std::string& uri);

}  // namespace station
