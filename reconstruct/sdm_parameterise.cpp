// SDM projection of a mesh onto a plane, sphere or cylinder (paper Fig. 6).
#include <cmath>

#include "core/error.h"
#include "reconstruct/sdm.h"
#include "reconstruct/sdm_internal.h"

namespace station {

ParameterisationResult sdm_parameterise(const Mesh&, SimpleSurface, const SdmParams&, int) {
  throw InvalidInput("sdm_parameterise: not implemented yet");
}

}  // namespace station
