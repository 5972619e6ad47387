// "sim:turntable": the virtual bench's stepper-driven table. It only moves an
// angle on the shared bench; the synthetic scanner reads it at every grab.
#include <cmath>

#include "core/error.h"
#include "sim/bench.h"

namespace station::sim {
namespace {

class SimTurntable final : public Turntable {
 public:
  SimTurntable(DeviceUri uri, std::shared_ptr<Bench> bench)
      : uri_(std::move(uri)), bench_(std::move(bench)) {
    for (const auto& [key, value] : uri_.options) {
      if (key == "steps") {
        const long long n = parse_int_option(uri_.text, key, value);
        require_option(n >= 1 && n <= 100000000, uri_.text, key, value,
                       "must be in [1, 100000000]");
        steps_ = int(n);
      } else {
        unknown_option(uri_.text, key, "steps");
      }
    }
  }

  void open() override { open_ = true; }
  void close() override { open_ = false; }

  void home() override {
    require_open("home");
    bench_->set_angle_deg(0);
  }

  void rotate_to(double degrees) override {
    require_open("rotate_to");
    if (!std::isfinite(degrees))
      throw DeviceError(uri_.text + ": rotate_to: angle " + std::to_string(degrees) +
                        " is not a finite number");
    // Wrap into [0, 360), then snap to the nearest motor step as a stepper would.
    double wrapped = std::fmod(degrees, 360.0);
    if (wrapped < 0) wrapped += 360.0;
    long long step = std::llround(wrapped / 360.0 * steps_);
    if (step >= steps_) step -= steps_;
    bench_->set_angle_deg(double(step) * 360.0 / steps_);
  }

  double angle() const override { return bench_->angle_deg(); }
  int steps_per_revolution() const override { return steps_; }
  std::string uri() const override { return uri_.text; }

 private:
  void require_open(const char* what) const {
    if (!open_) throw DeviceError(uri_.text + ": " + what + "() before open()");
  }

  DeviceUri uri_;
  std::shared_ptr<Bench> bench_;
  int steps_ = 3200;
  bool open_ = false;
};

}  // namespace

std::unique_ptr<Turntable> make_sim_turntable(const DeviceUri& uri, DeviceContext& context) {
  return std::make_unique<SimTurntable>(uri, bench_of(context));
}

}  // namespace station::sim
