// BSDFs as a flat node list (nested ones refer to children by index).
// Convention (Mitsuba 3's): local frame z = normal, wi points to the previous
// path vertex (camera side), wo is the sampled direction; eval returns
// f(wi, wo) * |cos(wo)|; radiance transport (camera paths).
#pragma once

#include <string>
#include <vector>

#include "core/math.h"
#include "scene/interaction.h"
#include "scene/microfacet.h"
#include "scene/texture.h"

namespace mpg {

enum class BSDFType {
  Diffuse, Conductor, RoughConductor, Dielectric, RoughDielectric, ThinDielectric, Plastic,
  TwoSided, NormalMap, Null
};

struct BSDF {
  BSDFType type = BSDFType::Diffuse;
  int reflectance = -1;               // texture ids
  int specular_reflectance = -1;
  int specular_transmittance = -1;
  Color eta_c{0.f}, k_c{1.f};         // conductor complex IOR
  float eta = 1.5046f;                // dielectric/plastic: int_ior / ext_ior
  Microfacet mf;
  bool nonlinear = false;             // plastic
  float fdr_int = 0.f;                // plastic: diffuse Fresnel reflectance inside
  float specular_sampling_weight = 0.5f;
  int front = -1, back = -1;          // twosided
  int nested = -1, normalmap = -1;    // normalmap: child BSDF, texture id

  bool is_delta() const {
    return type == BSDFType::Conductor || type == BSDFType::Dielectric ||
           type == BSDFType::ThinDielectric || type == BSDFType::Null;
  }
};

struct BSDFSample {
  Vec3 wo{0.f};        // local
  Color weight{0.f};   // f * |cos| / pdf  (delta: the discrete weight)
  float pdf = 0.f;
  float eta = 1.f;     // relative IOR crossed (1 for reflection)
  bool delta = false;
  bool transmission = false;
  bool null = false;
};

// A BSDF resolved at a hit: leaf node and its shading frame after twosided and
// normal map nodes have been applied.
struct BSDFContext {
  const BSDF* leaf = nullptr;
  Frame frame;          // frame the leaf works in
  Frame base;           // unperturbed shading frame (normal map side check)
  bool perturbed = false;
  Vec2 uv{0.f};
};

class BSDFSet {
 public:
  std::vector<BSDF> nodes;
  std::vector<Texture> textures;

  BSDFContext resolve(int id, const SurfaceInteraction& si) const;
  // Whether evaluating BSDF `id` reads texture coordinates (bitmap/checkerboard textures).
  bool uses_uv(int id) const;

  // Local-frame operations on a resolved context; wi and wo in world space.
  Color eval(const BSDFContext& c, const Vec3& wi, const Vec3& wo) const;
  float pdf(const BSDFContext& c, const Vec3& wi, const Vec3& wo) const;
  // u1 picks a lobe, u2 the direction. wo returned in world space in `wo_world`.
  BSDFSample sample(const BSDFContext& c, const Vec3& wi, float u1, const Vec2& u2,
                    Vec3& wo_world) const;

  Color tex(int id, const Vec2& uv, float fallback = 1.f) const {
    return id < 0 ? Color(fallback) : textures[size_t(id)].eval(uv);
  }

  // Leaf operations in the leaf's local frame.
  Color eval_local(const BSDF& b, const Vec2& uv, const Vec3& wi, const Vec3& wo) const;
  float pdf_local(const BSDF& b, const Vec2& uv, const Vec3& wi, const Vec3& wo) const;
  BSDFSample sample_local(const BSDF& b, const Vec2& uv, const Vec3& wi, float u1,
                          const Vec2& u2) const;
};

}  // namespace mpg
