// The manifold walk (Jakob & Marschner 2012; SMS, Zeltner et al. 2020, Sec. 4):
// Newton iterations on the specular constraints of a chain
// x_D, x_1..x_n, x_L with reprojection onto the surfaces by ray tracing.
//
// Each specular vertex carries a local chart (u, v) -> (position, shading
// normal) around its current position; the constraint C_i depends on the
// charts of x_{i-1}, x_i, x_{i+1}, so dC/d(u,v) is block tridiagonal with 2x2
// blocks, solved in O(n) (method-notes Sec. 2). The blocks are exact
// derivatives obtained by forward-mode differentiation (dual.h).
#pragma once

#include <glm/glm.hpp>

#include <array>
#include <string>
#include <vector>

#include "scene/scene.h"

namespace mpg {

using DVec3 = glm::dvec3;

enum class ConstraintForm {
  Direction,   // tangential components of (w_o - w_o'), w_o' the ideal specular direction (default)
  Angle,       // (theta, phi) differences in the shading frame (SMS's form; singular at the pole)
  HalfVector,  // tangential components of the generalised half vector
};

enum class WalkFailure {
  None = 0,
  SingularJacobian,
  TotalInternalReflection,
  VanishingSegment,
  Stuck,
  LeftSurface,     // reprojection hit another shape, nothing, or left the chain order
  StepTooSmall,
  MaxIterations,
  WrongHemisphere, // converged to a configuration the vertex type does not allow
  Occluded,        // last segment to the light blocked
  NotSpecular,     // a vertex's BSDF is not a smooth reflector/refractor for its letter
  Count            // (Stats::walk_failures has this many entries)
};
const char* walk_failure_name(WalkFailure f);

struct WalkConfig {
  double threshold = 1e-5;     // max |C_i| at convergence (SMS/MPG default)
  int max_iterations = 20;     // SMS/MPG default
  // The line search halves beta down to min_step (then `step_too_small`); with
  // step_halvings >= 0, iterations after the first stop that many halvings below
  // the beta they start from (-1: no such limit).
  double min_step = 1.0 / 1024.0;
  int step_halvings = -1;
  double min_segment = 1e-6;   // relative to the scene size
  double min_det = 1e-14;      // |det| of a 2x2 pivot below this is singular
  float glossy_threshold = 0.1f;  // rough interfaces with alpha below this are chain vertices
  ConstraintForm form = ConstraintForm::Direction;
  bool record_residuals = false;  // fill WalkResult::residuals (tests)
};

// One specular vertex with its chart.
struct ManifoldVertex {
  int shape = -1, prim = -1;
  bool reflect = true;   // letter: R or T
  double eta = 1.0;      // int_ior / ext_ior of the BSDF (refraction)
  bool dielectric = false;
  DVec3 p{0.0};
  // mesh chart: p(u,v) = p + u e1 + v e2, unnormalised normal N(u,v) = nb + u dn1 + v dn2
  DVec3 e1{0.0}, e2{0.0}, nb{0.0}, dn1{0.0}, dn2{0.0};
  // sphere chart: p(u,v) = c + r normalize(p + u e1 + v e2 - c)
  bool sphere = false;
  DVec3 center{0.0};
  double radius = 0.0;
  double normal_sign = 1.0;  // -1 with flip_normals
  // normal map: the shading normal is perturbed by a tangent-space texture
  // (as BSDFSet::resolve does); uv and dp/du follow the chart.
  const Texture* nmap = nullptr;
  glm::dvec2 uv0{0.0}, duv1{0.0}, duv2{0.0};  // mesh: uv(u,v) = uv0 + u duv1 + v duv2
  DVec3 dpdu{0.0};                            // mesh: constant per triangle
  // glossy vertex (MPG Sec. 5.7): a rough interface treated as a smooth one
  // whose normal is the offset microfacet normal m_local (in the shading frame
  // with s along e1), drawn from D(m) cos(theta_m) with the uniform pair offset_u.
  const Microfacet* mf = nullptr;
  glm::dvec3 m_local{0.0, 0.0, 1.0};
  Vec2 offset_u{0.5f};
  DVec3 n{0.0};              // shading normal at p
  DVec3 ng{0.0};             // geometric normal at p
  Vec2 uv{0.f};
};

struct ManifoldChain {
  DVec3 xD{0.0}, xL{0.0};
  DVec3 nD{0.0}, nL{0.0};   // normals at the endpoints (for offsets and charts)
  std::vector<ManifoldVertex> v;
};

// What a walk would have done under each step_halvings limit H = 0 .. 10,
// read off one walk (exact for the full search, and for H below an active
// limit): the limit stops the walk at the first iteration after the first
// whose line search rejects more than H tries, after H + 1 of them. The last
// slot, kFullSearch, is the walk as configured. With the default min_step,
// H = 10 is the full search too. mpg's training picks its render's limit from
// these (ChainParams::count_limits; design-notes "Step control").
inline constexpr int kHalvingSlots = 12;
inline constexpr int kFullSearch = kHalvingSlots - 1;

struct WalkResult {
  bool converged = false;
  WalkFailure failure = WalkFailure::None;
  int iterations = 0;
  int reprojections = 0;  // line-search tries (each reprojects every vertex)
  int off_surface = 0;    // of which: the moved chain did not land on its shapes
  int later_rejections = 0;  // the most rejected tries of one iteration after the first
  std::array<int, kHalvingSlots> limited_tries{};  // tries under step_halvings = H; [kFullSearch]: all
  std::vector<double> residuals;  // max |C| per iteration (for the convergence tests)
};

class ManifoldWalk {
 public:
  ManifoldWalk(const Scene& scene, WalkConfig cfg) : scene_(scene), cfg_(cfg) {}

  // Make a vertex (with its chart) from a surface hit; the letter decides R/T.
  // `offset_u` is the uniform pair that draws the offset normal when the surface
  // is glossy (required there, ignored on smooth surfaces).
  bool make_vertex(const SurfaceInteraction& si, bool reflect, ManifoldVertex& out,
                   const Vec2* offset_u = nullptr) const;
  // The same, with the hit point recomputed in double precision from the ray
  // (o, d): Embree's float hit limits the residual to ~1e-6 otherwise.
  bool make_vertex_refined(const SurfaceInteraction& si, const DVec3& o, const DVec3& d,
                           bool reflect, ManifoldVertex& out, const Vec2* offset_u = nullptr) const;

  // Newton iterations with reprojection; `chain` is updated in place.
  WalkResult solve(ManifoldChain& chain) const;

  // Constraint values (2 per vertex) of the current chain; false on TIR.
  bool constraints(const ManifoldChain& chain, std::vector<double>& C) const;

  // Jacobian blocks by forward differentiation: A_i = dC_i/dx_{i-1}, B_i = dC_i/dx_i,
  // D_i = dC_i/dx_{i+1} (2x2 each, row-major), plus dC_1/dx_D and dC_n/dx_L with
  // respect to orthonormal tangent charts at the endpoints (each skipped when null).
  bool jacobian(const ManifoldChain& chain, std::vector<double>& A, std::vector<double>& B,
                std::vector<double>& D, double dCn_dL[4], double dC1_dD[4]) const;

  // Generalised geometry terms of a converged chain (method-notes Sec. 4):
  // area light: |d omega_D / dA_L| (solid angle at x_D per unit area at x_L);
  // point light: |d omega_L / dA_D| (solid angle at x_L per unit area at x_D).
  bool geometry_area(const ManifoldChain& chain, double& G) const;
  bool geometry_point(const ManifoldChain& chain, double& G) const;

  // Trace a seed chain from xD along `dir` following the letters of `tau`
  // (R: mirror reflection, T: refraction about the shading normal).
  bool trace_seed(const DVec3& xD, const DVec3& nD, const DVec3& dir, const std::string& tau,
                  ManifoldChain& chain, WalkFailure& why, const std::vector<Vec2>* offsets = nullptr) const;

  // Solve the block-tridiagonal system J X = R (R: n x 2 x m, m right-hand sides).
  bool solve_tridiagonal(const std::vector<double>& A, const std::vector<double>& B,
                         const std::vector<double>& D, std::vector<double>& R, int m) const;

  const WalkConfig& config() const { return cfg_; }
  // Ideal specular scattering of the direction toward the previous vertex `wi`
  // about the vertex normal `n` (reflection, or refraction with relative IOR
  // `eta` = int/ext); false on total internal reflection.
  static bool scatter(const DVec3& wi, const DVec3& n, double eta, bool reflect, DVec3& wo);
  // The vertex moved by (du, dv) in its chart (position and shading normal); for tests.
  static ManifoldVertex moved(const ManifoldVertex& v, double du, double dv);

 private:
  WalkResult solve_walk(ManifoldChain& chain) const;  // solve() without the limits' tail
  bool reproject(const ManifoldChain& from, const std::vector<DVec3>& targets, ManifoldChain& out,
                 WalkFailure& why) const;
  const Scene& scene_;
  WalkConfig cfg_;
};

}  // namespace mpg
