#include "reconstruct/colour_transfer.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "core/kdtree.h"

namespace station {

void transfer_colours(Mesh& mesh, const Cloud& coloured, const ColourTransferParams& params) {
  if (coloured.empty() || !coloured.has_colours())
    throw InvalidInput("colour transfer: the cloud has no colours");
  if (params.neighbours < 1) throw InvalidInput("colour transfer: neighbours must be >= 1");
  const PointIndex index(coloured.points);
  mesh.colours.assign(mesh.vertices.size(), Rgb{});
  tbb::task_arena arena(params.threads > 0 ? params.threads : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, mesh.vertices.size(), 512),
                      [&](const auto& range) {
      for (std::size_t v = range.begin(); v != range.end(); ++v) {
        const auto nn = index.knn(mesh.vertices[v], params.neighbours);
        double sum[3] = {0, 0, 0}, wsum = 0;
        for (const auto& [i, d] : nn) {
          // A vertex on top of an input point takes its colour.
          const double w = 1.0 / std::max(double(d), 1e-12);
          sum[0] += w * coloured.colours[i].r;
          sum[1] += w * coloured.colours[i].g;
          sum[2] += w * coloured.colours[i].b;
          wsum += w;
        }
        auto ch = [&](double s) { return std::uint8_t(std::clamp(std::lround(s / wsum), 0L, 255L)); };
        mesh.colours[v] = {ch(sum[0]), ch(sum[1]), ch(sum[2])};
      }
    });
  });
}

}  // namespace station
