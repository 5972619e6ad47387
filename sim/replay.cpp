// "sim:replay?session=DIR": a recorded session played back as a live scanner.
//
// View order: sequential (view 0, 1, 2, ...) until the views run out, then
// DeviceError "no more views". Once a sim:turntable of the same registry has
// moved (home or rotate_to), each grab instead returns the view whose recorded
// turntable angle is closest (circularly) to the table's current angle, so a
// capture loop that rotates and then grabs replays the view recorded at that
// angle; ties go to a view not yet replayed, then to the lower index. Views
// without an angle are only reachable sequentially, and a session without any
// angle is always replayed sequentially.
#include <algorithm>
#include <chrono>
#include <cmath>

#include "capture/session.h"
#include "core/error.h"
#include "sim/bench.h"

namespace station::sim {
namespace {

double circular_distance_deg(double a, double b) {
  const double d = std::fmod(std::abs(a - b), 360.0);
  return d > 180.0 ? 360.0 - d : d;
}

class ReplayScanner final : public Scanner {
 public:
  ReplayScanner(DeviceUri uri, std::shared_ptr<Bench> bench)
      : uri_(std::move(uri)), bench_(std::move(bench)) {
    apply_options(uri_.options);
  }

  void open() override {
    try {
      session_.emplace(Session::open(dir_));
    } catch (const Error& e) {
      throw DeviceError(uri_.text + ": " + e.what());
    }
    replayed_.assign(session_->manifest().views.size(), false);
    next_ = 0;
  }

  void close() override { session_.reset(); }

  void configure(const DeviceOptions& options) override {
    const fs::path before = dir_;
    apply_options(options);
    if (session_ && dir_ != before) open();
  }

  ScannerCapabilities capabilities() const override {
    ScannerCapabilities caps;
    caps.points = true;
    if (!session_) return caps;
    const SessionManifest& m = session_->manifest();
    for (const ViewRecord& v : m.views) caps.colour = caps.colour || !v.colour_image.empty();
    if (m.intrinsics) caps.intrinsics = *m.intrinsics;
    caps.axis = m.axis;
    return caps;
  }

  Frame grab() override {
    if (!session_) throw DeviceError(uri_.text + ": grab() before open()");
    const SessionManifest& m = session_->manifest();
    std::optional<std::size_t> pick;
    if (bench_->moves() > 0) pick = closest_to_angle(bench_->angle_deg());
    if (!pick) {
      if (next_ >= m.views.size())
        throw DeviceError(uri_.text + ": no more views (" + std::to_string(m.views.size()) +
                          " recorded)");
      pick = next_++;
    }
    const ViewRecord& rec = m.views[*pick];
    Frame frame;
    try {
      frame.points = session_->load_view(*pick);
    } catch (const Error& e) {
      throw DeviceError(uri_.text + ": " + e.what());
    }
    if (m.intrinsics) frame.intrinsics = *m.intrinsics;
    if (!rec.colour_image.empty()) load_colour(session_->dir() / rec.colour_image, frame);
    frame.timestamp = rec.timestamp ? *rec.timestamp
                                    : std::chrono::duration<double>(
                                          std::chrono::system_clock::now().time_since_epoch())
                                          .count();
    frame.reference_pose = rec.reference_pose;
    replayed_[*pick] = true;
    return frame;
  }

  std::string uri() const override { return uri_.text; }

 private:
  void apply_options(const DeviceOptions& options) {
    for (const auto& [key, value] : options) {
      if (key == "session") {
        require_option(!value.empty(), uri_.text, key, value, "empty path");
        dir_ = value;
      } else {
        unknown_option(uri_.text, key, "session");
      }
    }
    if (dir_.empty())
      throw DeviceError(uri_.text + ": option 'session' missing (sim:replay?session=DIR)");
  }

  std::optional<std::size_t> closest_to_angle(double angle) const {
    const auto& views = session_->manifest().views;
    std::optional<std::size_t> best;
    double best_d = 0;
    for (std::size_t i = 0; i < views.size(); ++i) {
      if (!views[i].angle_deg) continue;
      const double d = circular_distance_deg(*views[i].angle_deg, angle);
      const bool tie = best && std::abs(d - best_d) <= 1e-9;
      if (!best || (!tie && d < best_d) || (tie && replayed_[*best] && !replayed_[i])) {
        best = i;
        best_d = d;
      }
    }
    return best;
  }

  // Colour images are recorded as PNG; frames carry RGB rows.
  void load_colour(const fs::path& path, Frame& frame) const {
    Texture image;
    try {
      image = load_texture(path);
    } catch (const IoError& e) {
      throw DeviceError(uri_.text + ": " + e.what());
    }
    frame.colour = std::move(image.rgb);
    const int cols = image.width, rows = image.height;
    // Recorded intrinsics describe the colour image when the sizes agree;
    // otherwise only its size is known (no calibration is invented).
    const auto& k = session_->manifest().intrinsics;
    if (k && k->width == cols && k->height == rows) {
      frame.colour_intrinsics = *k;
    } else {
      frame.colour_intrinsics = Intrinsics{};
      frame.colour_intrinsics.width = cols;
      frame.colour_intrinsics.height = rows;
    }
  }

  DeviceUri uri_;
  std::shared_ptr<Bench> bench_;
  fs::path dir_;
  std::optional<Session> session_;
  std::vector<bool> replayed_;
  std::size_t next_ = 0;
};

}  // namespace

std::unique_ptr<Scanner> make_replay_scanner(const DeviceUri& uri, DeviceContext& context) {
  return std::make_unique<ReplayScanner>(uri, bench_of(context));
}

}  // namespace station::sim
