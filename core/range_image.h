#pragma once
// Where the sensor of a single range image stood, from its file: a cloud read from
// one depth camera's frame has a side the camera saw, and normals estimated for it
// should face the camera. Today only an organised PCD (HEIGHT > 1: one row per image
// row, as PCL writes a Kinect frame) says so; its VIEWPOINT's translation is the
// sensor's place in the points' frame (the origin when VIEWPOINT is absent, PCL's
// default). An unorganised PCD (HEIGHT 1) may be a merge of many views, whatever its
// VIEWPOINT says, and other formats carry no sensor: none.
#include <filesystem>
#include <optional>
#include <string>

#include "core/geometry.h"

namespace station {

/// The sensor position of `path` when it is one range image (above); none otherwise or
/// when the header cannot be read (the reader reports that).
std::optional<Vec3f> range_image_sensor(const std::filesystem::path& path);

/// read_cloud; where the cloud is one range image (above) and has no usable normals,
/// its normals are estimated (PCA, 12 neighbours) and turned to face its sensor, and
/// `note` says so (empty otherwise). The surface stage's own orientation (a spanning
/// tree, "up" first) turned a Kinect frame's surface away from the camera: 16-27 % of
/// the faces faced it.
Cloud read_cloud_oriented(const std::filesystem::path& path, int threads, std::string& note);

}  // namespace station
