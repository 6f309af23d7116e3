// Per-pass statistics, accumulated per thread and merged.
#pragma once

#include <cstdint>
#include <map>
#include <string>

namespace mpg {

struct Stats {
  uint64_t samples = 0;
  uint64_t camera_rays = 0;
  uint64_t rays = 0;           // intersection queries
  uint64_t shadow_rays = 0;
  uint64_t rejected_nan = 0;   // samples with NaN, dropped (contribute zero)
  uint64_t rejected_inf = 0;
  uint64_t rejected_negative = 0;
  uint64_t depth_capped = 0;   // paths stopped by the hard bounce cap
  uint64_t path_vertices = 0;

  void merge(const Stats& o) {
    samples += o.samples; camera_rays += o.camera_rays; rays += o.rays;
    shadow_rays += o.shadow_rays; rejected_nan += o.rejected_nan; rejected_inf += o.rejected_inf;
    rejected_negative += o.rejected_negative; depth_capped += o.depth_capped;
    path_vertices += o.path_vertices;
  }
  std::map<std::string, double> to_map() const {
    return {{"samples", double(samples)},           {"camera_rays", double(camera_rays)},
            {"rays", double(rays)},                 {"shadow_rays", double(shadow_rays)},
            {"rejected_nan", double(rejected_nan)}, {"rejected_inf", double(rejected_inf)},
            {"rejected_negative", double(rejected_negative)},
            {"depth_capped", double(depth_capped)}, {"path_vertices", double(path_vertices)}};
  }
};

}  // namespace mpg
