#pragma once
// Detects V4L2 video devices for `station devices`, through the SysCalls seam
// (so it is tested with a fake kernel). Capture through V4L2 is a later issue;
// until then detected cameras are listed as unavailable.
#include <string>
#include <vector>

#include "drivers/registry.h"
#include "drivers/syscalls.h"

namespace station {

/// Queries each path with VIDIOC_QUERYCAP; paths that fail to open or answer
/// are skipped. Devices without video capture capability are skipped too.
std::vector<DeviceInfo> probe_v4l2(SysCalls& sys, const std::vector<std::string>& paths);

/// /dev/video0 ... /dev/video63 that exist.
std::vector<std::string> v4l2_device_paths();

/// Adds the V4L2 lister to the registry (no factory yet: see the header comment).
void register_v4l2_probe(DeviceRegistry& registry, std::shared_ptr<SysCalls> sys);

}  // namespace station
