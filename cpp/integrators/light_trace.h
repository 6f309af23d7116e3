// Light tracing of the point and spot lights' caustics seen by the camera,
// and optionally the area lights' (docs/design-notes.md, "Light tracing the
// point lights' caustics").
//
// A point light's caustic on a diffuse floor is its irradiance through a
// specular chain, E(x) = I T |d omega_L / dA_x|, which is unbounded at a focus
// (a ball lens focuses to a spot, a fold to a line): an estimator that
// evaluates E at points the camera picks (the chain estimator, SMS, MPG) has
// a second moment ~ int E^2 dA, infinite or nearly so there. A photon traced
// from the light lands with density proportional to E, so its splat carries a
// bounded weight: the same integral with finite variance (Veach 1997 Sec. 10.2,
// the light-tracing strategy of bidirectional path tracing).
//
// The path set is partitioned, never shared: for a separator x_D hit by the
// camera ray itself (loop depth 0) the chain estimator leaves out its chains
// to point and spot lights (Stats::chain_skip_delta_lights), and the photons
// of this tracer bring exactly those paths: light -> 1..nmax chain vertices
// (the estimator's chain shapes and BSDFs) -> separator x_D -> camera, nmax as
// the estimator's at depth 0, of the types it owns there (sms: its one). The
// path tracer never reaches a delta light, so nothing else produces them.
// Separators seen through glass stay the estimator's, unless `through`: then
// each photon is also connected to the pinhole by a camera-side chain of
// 1..camera_chain_max() vertices (ChainEstimator::connect_point), and the
// camera path's separators behind that many chain vertices leave their
// point-light chains to the photons too (path.cpp, chain_prefix).
//
// With `area` (PathParams::light_trace_area) the area chain lights are traced
// too, seen directly only: a photon leaves a point uniform by area on the
// light (weight Le |cos(n_L, w)| A / (p_sel p_w)); at the camera's first hits
// the estimator skips their chains as well (Stats::chain_skip_area_lights)
// and the path tracer drops its paths that reach an area light through such a
// chain (Stats::lt_pt_dropped): the photons bring them whole. An area light's
// caustic is bounded, but the estimator's values at camera-chosen points
// carry K G, huge near the caustic's folds; the photons' are bounded there.
//
// Glossy mode (PathParams::light_trace_glossy; the second constructor): where
// no chain estimator runs because the casters are glossy under a normal map
// (the walk does not take those, docs/design-notes.md), the photons take the
// casters' caustics seen directly with no estimator at all. The casters are
// the shapes whose BSDF is smooth or rough below the glossy threshold, under
// normal maps or not (caster_vertex; not emitters, not caustic_receiver
// shapes); a photon follows their BSDF samples, glossy lobes included, with
// the adjoint's weights, and the path set is: camera -> x_D (the camera ray's
// first hit, not delta, not a caster) -> 1..nmax caster vertices -> a traced
// light. The path tracer drops exactly those paths, both the NEE at the last
// caster and the BSDF sample that hits the light (path.cpp, `gl_n`).
//
// Splat of a photon at x_D with flux weight Phi (intensity / direction pdf
// times the chain's discrete weights), x_D at distance d from the pinhole c,
// camera axis angle theta_c (pixel value = mean of the radiance over the
// pixel's area A_pix on the plane at unit distance):
//
//   Phi * f_s(w_c, w_l) |cos(n_s, w_l)| / |cos(n_g, w_l)| * |cos(n_g, w_c)| / (A_pix cos^3 theta_c d^2)
//
// (the BSDF as the camera path evaluates it, with the adjoint's shading-normal
// correction; Veach 1997 Sec. 5.3). At chain vertices the radiance-mode weight
// of a refraction, (eta_i / eta_t)^2 (1 - F) / (1 - F), is a flux weight of 1.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/rng.h"
#include "manifold/chain_estimator.h"
#include "render/stats.h"
#include "scene/scene.h"

namespace mpg {

struct LightSplat {
  uint32_t pixel = 0;   // index into the crop window, y * crop_w + x
  Color value{0.f};     // the photon's contribution to that pixel (not yet divided by the photon count)
};

class LightTracer {
 public:
  // Built for a chain estimator at a given max_depth (the path tracer's). usable()
  // false (with why()) when the scene gives it nothing to do or it cannot
  // take the estimator's paths exactly.
  // through: also connect each photon's x_D to the camera through chains
  // (camera_chain_max(); sms_star and mpg only).
  // area: trace the area chain lights too (else point and spot lights only).
  LightTracer(const Scene& scene, const ChainEstimator& chains, int max_depth, bool through = false,
              float photons_per_sample = 1.f, bool area = false);
  // Glossy mode (see above): no chain estimator; casters are the shapes whose
  // BSDF is below glossy_threshold (normal-mapped or not), chains of at most
  // nmax of them (the estimator's max_chain_len at the first hit).
  LightTracer(const Scene& scene, int max_depth, int nmax, float glossy_threshold, float photons_per_sample,
              bool area);
  bool glossy() const { return glossy_; }
  // The longest chain of caster vertices a photon follows.
  int max_chain() const { return nmax_; }
  // Is the hit (shape, resolved BSDF) a caster vertex, one a photon passes?
  bool caster_vertex(int shape, const BSDF& leaf) const;
  bool usable() const { return usable_; }
  const Scene& scene() const { return scene_; }
  // Photons per camera sample (PathParams::light_trace): each render pass
  // traces this times its spp times the crop's pixels.
  float photons_per_sample() const { return rate_; }
  // The longest camera-side chain a photon is connected through (0: none):
  // the camera path's separators behind at most that many chain vertices
  // leave their point/spot-light chains to the photons as well.
  int camera_chain_max() const { return mmax_cam_; }
  // Are the area chain lights traced too (seen directly only)? Then the
  // camera's first hits leave their area-light chains to the photons as well:
  // the estimator skips them (Stats::chain_skip_area_lights) and the path
  // tracer drops the paths that reach an area light through such a chain.
  bool traces_area() const { return area_; }
  // Does the tracer emit photons from emitter e?
  bool traces_emitter(int e) const { return e >= 0 && size_t(e) < traced_.size() && traced_[size_t(e)] != 0; }
  const std::string& why() const { return why_; }
  // One photon: emitted, traced through chain vertices, splatted (at most one
  // splat appended). Draws from rng only.
  void trace(PCG32& rng, Stats& st, std::vector<LightSplat>& out) const;

 private:
  // The photon's flux arriving at separator x_D (si, its wi toward the chain)
  // seen directly: the camera connection and its splat.
  void connect(const SurfaceInteraction& si, const Shape& shape, const Color& flux, std::vector<LightSplat>& out,
               Stats& st) const;
  // ... through a chain to the camera (ChainEstimator::connect_point), for
  // the light chain of letters tau_l (x_D -> x_L order).
  void connect_chain(const SurfaceInteraction& si, const Shape& shape, const Color& flux, const std::string& tau_l,
                     PCG32& rng, std::vector<LightSplat>& out, Stats& st) const;
  // Both connections' splat: x_D's BSDF toward w_out (the camera or the
  // camera-side chain) against the photon's direction, the camera's view of
  // the point `from` (normal from_ng) unoccluded past the near plane, and
  // flux f / |cos(n_g, w_l)| G / (A_pix cos^3 theta_c), G the solid angle at
  // the camera per unit area at x_D (times the chain's weights). false: none.
  bool splat(SurfaceInteraction si, const Shape& shape, const Vec3& w_out, const Vec3& from, const Vec3& from_ng,
             float t_near, const Color& G, const Color& flux, uint32_t pixel, float cos_c,
             std::vector<LightSplat>& out, Stats& st) const;
  // The pixel (crop index) the camera sees the point p in, with the cosine of
  // its direction to the optical axis and the world distance at which the
  // camera ray starts (the near clip); false outside the crop or the clip range.
  bool project(const Vec3& p, uint32_t& pixel, float& cos_c, float& t_near) const;
  // The emitters, camera and aim shared by both modes (false: why_ says why)
  bool init_common(const std::vector<char>& casters);
  const Scene& scene_;
  const ChainEstimator* chains_ = nullptr;   // (null in glossy mode)
  bool glossy_ = false;
  float glossy_threshold_ = 0.f;
  std::vector<char> caster_shape_;   // glossy mode: shape index -> caster
  bool usable_ = false;
  std::string why_;
  float rate_ = 1.f;
  int nmax_ = 0;
  int mmax_cam_ = 0;
  uint32_t max_depth_ = 0;
  bool area_ = false;
  std::vector<int> lights_;          // point and spot chain lights (and area ones with area_)
  DiscreteDistribution light_dist_;  // by power
  std::vector<char> traced_;         // emitter index -> in lights_
  Vec3 bound_c_{0.f};                // bounding sphere of the chain shapes
  double bound_r_ = 0.0;
  // camera
  Mat4 to_local_{1.f};
  Vec3 cam_o_{0.f}, cam_fwd_{0.f, 0.f, 1.f};
  double inv_a_pix_ = 0.0;
};

}  // namespace mpg
