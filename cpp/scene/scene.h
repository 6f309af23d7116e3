// The scene: shapes in an Embree 3 BVH, BSDFs, emitters, camera.
#pragma once

#include <embree3/rtcore.h>

#include <string>
#include <vector>

#include "core/distribution.h"
#include "scene/bsdf.h"
#include "scene/camera.h"
#include "scene/emitter.h"
#include "scene/interaction.h"
#include "scene/shape.h"

namespace mpg {

struct EmitterSample {
  Vec3 wi{0.f};        // unit direction from the reference point toward the light
  float dist = kInf;   // distance to the light point (inf for infinite emitters)
  Vec3 p{0.f};         // point on the light (finite emitters)
  Color value{0.f};    // incident radiance (or I / r^2, E for delta lights)
  float pdf = 0.f;     // solid angle density times selection probability; for delta lights the probability
  bool delta = false;
  int emitter = -1;
};

struct DirectSphere {
  double cx, cy, cz, r2;
  unsigned shape;
};

class Scene {
 public:
  Scene();
  ~Scene();
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;

  BSDFSet bsdfs;
  std::vector<Shape> shapes;
  std::vector<Emitter> emitters;
  Camera camera;

  int add_shape(Shape s);
  int add_emitter(Emitter e);
  void commit();  // builds the BVH and light selection; throws std::runtime_error
  bool committed() const { return committed_; }

  SurfaceInteraction intersect(const Vec3& o, const Vec3& d, float tmin, float tmax) const;
  // Complete a hit record from Embree's (geometry, primitive, barycentrics, t).
  SurfaceInteraction make_interaction(const Vec3& o, const Vec3& d, float t, unsigned geom,
                                      unsigned prim, float bu, float bv) const;
  bool occluded(const Vec3& o, const Vec3& d, float tmin, float tmax) const;
  // Is the segment from the surface point p (geometric normal ng) to the
  // point `target` blocked? The ray leaves from p's offset origin and runs to
  // the target itself, stopping short of it by a relative 1e-4 (along the
  // direction from p itself it would cross an area light's plane short of
  // the target by about the offset / cos, more than that margin when the
  // offset, 1e-4 of the coordinates' size, is large against the distance:
  // the light would shadow itself).
  bool occluded_to(const Vec3& p, const Vec3& ng, const Vec3& target) const;

  EmitterSample sample_emitter(const Vec3& ref, float u_sel, const Vec2& u) const;
  // Density (solid angle at ref, selection included) that sample_emitter produced
  // the hit `si` on an area emitter, or an escaped direction for infinite emitter e.
  float pdf_emitter_hit(const Vec3& ref, const SurfaceInteraction& si) const;
  float pdf_emitter_escape(int e, const Vec3& d) const;
  Color emitted(const SurfaceInteraction& si) const;  // area radiance toward si.wi
  float emitter_pmf(int e) const { return light_dist_.pmf(size_t(light_index_[size_t(e)])); }

  Vec3 bbox_min{0.f}, bbox_max{0.f};
  float bound_radius() const { return 0.5f * glm::length(bbox_max - bbox_min); }
  Vec3 bound_center() const { return 0.5f * (bbox_min + bbox_max); }
  std::vector<int> infinite_emitters;

 private:
  RTCDevice device_ = nullptr;
  RTCScene rtc_ = nullptr;
  bool rtc_empty_ = true;  // no geometry in Embree's BVH (skip the call)
  // A few spheres are intersected analytically (in double) outside Embree: for
  // scenes with a handful of spheres this is cheaper than Embree's point
  // primitives and exact to double precision. More spheres go to Embree.
  std::vector<DirectSphere> direct_spheres_;
  static constexpr size_t kMaxDirectSpheres = 8;
  bool committed_ = false;
  DiscreteDistribution light_dist_;
  std::vector<int> light_list_;   // selection index -> emitter
  std::vector<int> light_index_;  // emitter -> selection index (-1 if never selected)
};

}  // namespace mpg
