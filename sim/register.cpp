#include "sim/bench.h"
#include "sim/sim.h"

namespace station {

void register_sim_devices(DeviceRegistry& registry) {
  registry.add_scanner("sim:synthetic", sim::make_synthetic_scanner, [] {
    return std::vector<DeviceInfo>{
        {"sim:synthetic?mesh=FILE", DeviceKind::kScanner,
         "simulated range + colour camera ray casting a mesh (OBJ+texture, PLY, OFF) on the "
         "virtual turntable; options in sim/sim.h",
         true}};
  });
  registry.add_scanner("sim:replay", sim::make_replay_scanner, [] {
    return std::vector<DeviceInfo>{{"sim:replay?session=DIR", DeviceKind::kScanner,
                                    "plays a recorded session back view by view (follows "
                                    "sim:turntable's angle once it has moved)",
                                    true}};
  });
  registry.add_turntable("sim:turntable", sim::make_sim_turntable, [] {
    return std::vector<DeviceInfo>{{"sim:turntable?steps=3200", DeviceKind::kTurntable,
                                    "virtual turntable sharing the bench with sim:synthetic",
                                    true}};
  });
}

}  // namespace station
