#pragma once
// Registers every real back-end the build has: serial turntables (horus:,
// fabscan:), V4L2 cameras (v4l2:), and, when their libraries were found at
// build time, the Kinect v1 (kinect:, libfreenect) and OpenNI2 cameras
// (openni:). `station devices` lists what is plugged
// in; serial ports are listed without being opened (opening resets Arduinos),
// so a listed port may hold either board or neither.
#include <memory>
#include <string>
#include <vector>

#include "drivers/registry.h"
#include "drivers/syscalls.h"

namespace station {

/// /dev/ttyUSB* and /dev/ttyACM* that exist, sorted.
std::vector<std::string> serial_port_paths();

void register_serial_turntables(DeviceRegistry& registry);
void register_v4l2_cameras(DeviceRegistry& registry, std::shared_ptr<SysCalls> sys);

/// Both of the above with the real kernel. Replaces register_v4l2_probe.
void register_real_devices(DeviceRegistry& registry);

}  // namespace station
