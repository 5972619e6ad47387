#include "station/render.h"

#include <Eigen/Geometry>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/error.h"

namespace station {

Image::Image(int w, int h, Rgb fill) : width(w), height(h), rgb(std::size_t(w) * h * 3) {
  for (std::size_t i = 0; i < rgb.size(); i += 3) {
    rgb[i] = fill.r;
    rgb[i + 1] = fill.g;
    rgb[i + 2] = fill.b;
  }
}

namespace {

/// World -> screen: x right, y down, depth = distance along the viewing direction
/// (smaller is nearer).
struct Projector {
  Vec3d right, up, forward, center;
  double scale = 1, cx = 0, cy = 0;

  Projector(const RenderView& v, const Aabb& box) {
    forward = -v.toward_eye.normalized();
    Vec3d u = v.up - v.up.dot(forward) * forward;
    if (u.norm() < 1e-9) u = forward.unitOrthogonal();
    up = u.normalized();
    // Right-handed: right x up = toward the eye = -forward.
    right = forward.cross(up).normalized();
    center = box.valid() ? Vec3d(box.center().cast<double>()) : Vec3d::Zero();
    const double radius = box.valid() ? std::max(1e-12, 0.5 * double(box.diagonal())) : 1.0;
    const double half = 0.5 * std::min(v.width, v.height) - v.margin;
    scale = std::max(1.0, half) / radius;
    cx = 0.5 * v.width;
    cy = 0.5 * v.height;
  }
  Vec3d project(const Vec3f& p) const {
    const Vec3d d = p.cast<double>() - center;
    return {cx + scale * d.dot(right), cy - scale * d.dot(up), d.dot(forward)};
  }
};

Rgb shade_colour(Rgb c, double cosine, const RenderOptions& o) {
  if (!o.shade) return c;
  const double k = o.ambient + (1 - o.ambient) * std::min(1.0, std::abs(cosine));
  auto s = [&](std::uint8_t v) { return std::uint8_t(std::clamp(std::lround(v * k), 0L, 255L)); };
  return {s(c.r), s(c.g), s(c.b)};
}

Aabb box_of(const RenderView& v, const std::vector<Vec3f>& points) {
  if (v.box.valid()) return v.box;
  Aabb b;
  for (const Vec3f& p : points)
    if (p.allFinite()) b.extend(p);
  return b;
}

}  // namespace

namespace {
/// A horizontal frame (front, left) for an up direction: front is +x made
/// orthogonal to up (or +y when up is along x).
void horizontal_frame(const Vec3d& up_in, Vec3d& up, Vec3d& front, Vec3d& left) {
  up = up_in.norm() > 0 ? up_in.normalized() : Vec3d::UnitZ();
  front = Vec3d::UnitX() - up.x() * up;
  if (front.norm() < 0.3) front = Vec3d::UnitY() - up.y() * up;
  front.normalize();
  left = up.cross(front);
}
}  // namespace

RenderView view_from_side(int quarter_turns, const Aabb& box, int size, const Vec3d& up_dir) {
  RenderView v;
  Vec3d up, front, left;
  horizontal_frame(up_dir, up, front, left);
  const double a = quarter_turns * M_PI / 2;
  v.toward_eye = (std::cos(a) * front + std::sin(a) * left + 0.25 * up).normalized();
  v.up = up;
  v.box = box;
  v.width = v.height = size;
  return v;
}

RenderView view_from_above(const Aabb& box, int size, const Vec3d& up_dir) {
  RenderView v;
  Vec3d up, front, left;
  horizontal_frame(up_dir, up, front, left);
  v.toward_eye = up;
  v.up = front;
  v.box = box;
  v.width = v.height = size;
  return v;
}

Image render_mesh(const Mesh& mesh, const RenderView& view, const RenderOptions& o) {
  if (view.width <= 0 || view.height <= 0) throw InvalidInput("render: empty image size");
  Image img(view.width, view.height, o.background);
  const Projector proj(view, box_of(view, mesh.vertices));
  std::vector<Vec3d> s(mesh.vertices.size());
  for (std::size_t i = 0; i < s.size(); ++i) s[i] = proj.project(mesh.vertices[i]);
  std::vector<double> zbuf(std::size_t(view.width) * view.height, std::numeric_limits<double>::infinity());
  const bool colours = o.use_colours && mesh.colours.size() == mesh.vertices.size();
  for (const Face& f : mesh.faces) {
    if ((f.array() < 0).any() || (f.array() >= int(s.size())).any()) continue;
    const Vec3d &a = s[f[0]], &b = s[f[1]], &c = s[f[2]];
    if (!a.allFinite() || !b.allFinite() || !c.allFinite()) continue;
    const double area = (b.x() - a.x()) * (c.y() - a.y()) - (b.y() - a.y()) * (c.x() - a.x());
    if (std::abs(area) < 1e-12) continue;
    const Vec3f& wa = mesh.vertices[f[0]];
    const Vec3f n = (mesh.vertices[f[1]] - wa).cross(mesh.vertices[f[2]] - wa);
    const double cosine = n.norm() > 0 ? n.normalized().cast<double>().dot(-proj.forward) : 1.0;
    const int x0 = std::max(0, int(std::floor(std::min({a.x(), b.x(), c.x()}))));
    const int x1 = std::min(view.width - 1, int(std::ceil(std::max({a.x(), b.x(), c.x()}))));
    const int y0 = std::max(0, int(std::floor(std::min({a.y(), b.y(), c.y()}))));
    const int y1 = std::min(view.height - 1, int(std::ceil(std::max({a.y(), b.y(), c.y()}))));
    for (int y = y0; y <= y1; ++y)
      for (int x = x0; x <= x1; ++x) {
        const double px = x + 0.5, py = y + 0.5;
        // Barycentric weights (any orientation: divide by the signed area).
        const double w0 = ((b.x() - px) * (c.y() - py) - (b.y() - py) * (c.x() - px)) / area;
        const double w1 = ((c.x() - px) * (a.y() - py) - (c.y() - py) * (a.x() - px)) / area;
        const double w2 = 1 - w0 - w1;
        if (w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9) continue;
        const double z = w0 * a.z() + w1 * b.z() + w2 * c.z();
        double& zb = zbuf[std::size_t(y) * view.width + x];
        if (z >= zb) continue;
        zb = z;
        Rgb col = o.base;
        if (colours) {
          const Rgb &ca = mesh.colours[f[0]], &cb = mesh.colours[f[1]], &cc = mesh.colours[f[2]];
          auto mix = [&](std::uint8_t u, std::uint8_t v, std::uint8_t t) {
            return std::uint8_t(std::clamp(std::lround(w0 * u + w1 * v + w2 * t), 0L, 255L));
          };
          col = {mix(ca.r, cb.r, cc.r), mix(ca.g, cb.g, cc.g), mix(ca.b, cb.b, cc.b)};
        }
        img.set(x, y, shade_colour(col, cosine, o));
      }
  }
  return img;
}

Image render_points(const Cloud& cloud, const RenderView& view, const RenderOptions& o,
                    const std::vector<Rgb>* colours) {
  if (view.width <= 0 || view.height <= 0) throw InvalidInput("render: empty image size");
  Image img(view.width, view.height, o.background);
  const Projector proj(view, box_of(view, cloud.points));
  std::vector<double> zbuf(std::size_t(view.width) * view.height, std::numeric_limits<double>::infinity());
  const std::vector<Rgb>* cols = colours && colours->size() == cloud.size()
                                     ? colours
                                     : (o.use_colours && cloud.colours.size() == cloud.size() ? &cloud.colours
                                                                                           : nullptr);
  const bool normals = cloud.normals.size() == cloud.size();
  const int r0 = -(o.point_size - 1) / 2, r1 = o.point_size / 2;
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const Vec3d s = proj.project(cloud.points[i]);
    if (!s.allFinite()) continue;
    const double cosine =
        normals && cloud.normals[i].allFinite() && cloud.normals[i].norm() > 0
            ? cloud.normals[i].normalized().cast<double>().dot(-proj.forward)
            : 1.0;
    const Rgb c = shade_colour(cols ? (*cols)[i] : o.base, cosine, o);
    const int px = int(std::floor(s.x())), py = int(std::floor(s.y()));
    for (int dy = r0; dy <= r1; ++dy)
      for (int dx = r0; dx <= r1; ++dx) {
        const int x = px + dx, y = py + dy;
        if (x < 0 || y < 0 || x >= view.width || y >= view.height) continue;
        double& zb = zbuf[std::size_t(y) * view.width + x];
        if (s.z() >= zb) continue;
        zb = s.z();
        img.set(x, y, c);
      }
  }
  return img;
}

std::string encode_png(const Image& image) {
  if (image.width <= 0 || image.height <= 0 || image.rgb.size() != std::size_t(image.width) * image.height * 3)
    throw InvalidInput("render: empty or inconsistent image");
  cv::Mat rgb(image.height, image.width, CV_8UC3, const_cast<std::uint8_t*>(image.rgb.data()));
  cv::Mat bgr;
  cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
  std::vector<uchar> buf;
  if (!cv::imencode(".png", bgr, buf)) throw InvalidInput("render: PNG encoding failed");
  return std::string(buf.begin(), buf.end());
}

std::string base64(const std::string& bytes) {
  static const char* table = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  std::size_t i = 0;
  for (; i + 2 < bytes.size(); i += 3) {
    const unsigned v = (unsigned char)bytes[i] << 16 | (unsigned char)bytes[i + 1] << 8 | (unsigned char)bytes[i + 2];
    out += table[v >> 18];
    out += table[(v >> 12) & 63];
    out += table[(v >> 6) & 63];
    out += table[v & 63];
  }
  if (i < bytes.size()) {
    unsigned v = (unsigned char)bytes[i] << 16;
    if (i + 1 < bytes.size()) v |= (unsigned char)bytes[i + 1] << 8;
    out += table[v >> 18];
    out += table[(v >> 12) & 63];
    out += i + 1 < bytes.size() ? table[(v >> 6) & 63] : '=';
    out += '=';
  }
  return out;
}

}  // namespace station
