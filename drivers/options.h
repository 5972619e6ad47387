#pragma once
// Readers of device options (the `options` of a profile's scanner or turntable,
// merged into its URI's query), shared by every driver.
#include <set>
#include <string>
#include <vector>

#include "drivers/scanner.h"

namespace station {

/// Option readers: DeviceError "URI: option KEY=VALUE: problem" on bad values.
double option_number(const DeviceOptions& options, const std::string& key, double fallback,
                     double min, double max, const std::string& uri);
int option_integer(const DeviceOptions& options, const std::string& key, int fallback, int min,
                   int max, const std::string& uri);
/// A whole string as a finite number (strtod, nothing left over, in range): the one
/// number reader of device options and URIs. False on anything else.
bool parse_number(const std::string& text, double& out);
/// The `count` comma-separated numbers of option `key` (empty when it is absent):
/// DeviceError "URI: option KEY: expected COUNT comma-separated numbers (WHAT), got 'VALUE'".
std::vector<double> option_numbers(const DeviceOptions& options, const std::string& key, int count,
                                   const std::string& what, const std::string& uri);
/// Option `key` (k1,k2,p1,p2,k3, OpenCV's order, as `station calibrate camera` writes
/// them) into k.distortion; k untouched when the option is absent.
void option_distortion(const DeviceOptions& options, const std::string& key, Intrinsics& k,
                       const std::string& uri);
/// DeviceError naming the first key not in `known`.
void reject_unknown_options(const DeviceOptions& options, const std::set<std::string>& known,
                            const std::string& uri);

}  // namespace station
