// Unidirectional path tracer: BSDF sampling + next-event estimation combined
// with the power heuristic (Veach 1997, Ch. 9). max_depth and rr_depth have
// Mitsuba 3's meaning so the same file gives the same expected image:
// max_depth = longest path in segments (1: only directly visible emitters,
// -1: unbounded); Russian roulette from depth rr_depth with continuation
// probability min(max(beta) * eta^2, 0.95).
#pragma once

#include <algorithm>
#include <memory>

#include "integrators/integrator.h"
#include "integrators/light_trace.h"
#include "manifold/chain_estimator.h"

namespace mpg {

struct PathParams {
  int max_depth = -1;
  int rr_depth = 5;
  bool hide_emitters = false;
  // The light that reaches the camera through delta scattering only (the
  // emitters seen directly or in ideal glass and mirrors: no separator, so no
  // NEE or chain estimate has it): All keeps it, Exclude leaves it out, Only
  // renders it alone (the path ends at its first non-delta vertex). Exclude +
  // Only = All, path by path: a reference splits the work this way
  // (mpg-bench reference --camera-delta path); mpg's delta split traces extra
  // Only paths (Li_delta, Stats::split_delta).
  enum class CameraDelta { All, Exclude, Only };
  CameraDelta camera_delta = CameraDelta::All;
  // Li_delta branches at its first delta_branch delta vertices with two lobes
  // (a dielectric's reflection and refraction): both are followed, each with
  // its discrete weight times its probability, instead of one drawn (0: off).
  int delta_branch = 0;
  // The delta split's extra camera paths at the points of a per-pixel
  // randomly shifted Sobol sequence (render.cpp), not independent positions.
  bool delta_split_sobol = false;
  int hard_depth_cap = 1024;  // safety net against unbounded loops (counted)
  // Photons per camera sample of the light tracer (integrators/light_trace.h;
  // chain integrators only; 0: off): with a point or spot chain light, the
  // chains to it from the camera's first hits are light traced instead of
  // estimated.
  float light_trace = 0.f;
  // ... and connect each photon to the camera through chains of the chain
  // shapes too (sms_star, mpg), so that a caustic seen in the glass is light
  // traced as well (LightTracer::camera_chain_max)
  bool light_trace_through = false;
  // ... and trace the area chain lights' photons too (seen directly only):
  // their chains from the camera's first hits are then the photons' as well
  // (the estimator skips them, the path tracer drops the paths that hit
  // them; LightTracer::traces_area)
  bool light_trace_area = false;
  // Photons per camera sample where no chain estimator runs because the
  // casters are glossy under a normal map (the walk does not take them):
  // the casters' caustics the camera sees directly are then light traced
  // from every point, spot and area light (LightTracer's glossy mode) and the
  // path tracer drops those paths (0: off)
  float light_trace_glossy = 0.f;
  // Glints (ChainEstimator::glint; chain integrators only; 0: off): the area
  // chain lights whose angular size is below this many pixels are found from
  // the camera through chains by walks (the path tracer drops its paths
  // camera -> 1..mmax chain vertices -> such a light).
  float glints = 0.f;
};

// With a ChainEstimator (integrators `sms` and `sms_star`) every separator also
// estimates the light through specular chains, and the BSDF-sampled paths the
// estimator owns are dropped (design.md, "No double counting").
class PathIntegrator : public Integrator {
 public:
  explicit PathIntegrator(PathParams p, std::shared_ptr<const ChainEstimator> chains = nullptr)
      : p_(p), chains_(std::move(chains)) {
    if (chains_ && !chains_->active()) {
      // effects follow the scene; glossy casters' caustics are still light
      // traced on request (LightTracer's glossy mode)
      if (p_.light_trace_glossy > 0.f && p_.camera_delta != PathParams::CameraDelta::Only) {
        // (silent when it cannot run: mpg's default asks for it on every scene)
        auto lt = std::make_shared<LightTracer>(chains_->scene(), p_.max_depth,
                                                chains_->max_chain_len(0, uint32_t(p_.max_depth)),
                                                chains_->glossy_threshold(), p_.light_trace_glossy, true);
        if (lt->usable()) lt_ = std::move(lt);
      }
      chains_.reset();
    }
    if (chains_ && p_.light_trace > 0.f && p_.camera_delta != PathParams::CameraDelta::Only) {
      auto lt = std::make_shared<LightTracer>(chains_->scene(), *chains_, p_.max_depth, p_.light_trace_through,
                                              p_.light_trace, p_.light_trace_area);
      if (lt->usable()) lt_ = std::move(lt);
      else lt_off_ = lt->why();
    }
    if (chains_ && p_.glints > 0.f) gl_ = chains_->glint_lights(p_.glints, p_.max_depth);
  }
  const LightTracer* light_tracer() const override { return lt_.get(); }
  // (not in Exclude mode, which leaves out every path seen through delta
  // scattering only, the glints' included: exclude + only = all)
  bool glints_on() const override { return gl_.usable() && p_.camera_delta != PathParams::CameraDelta::Exclude; }
  const ChainEstimator::GlintLights& glint_lights() const { return gl_; }
  Color glint(const Vec3& o, const Vec3& d, const SurfaceInteraction& si, PCG32& rng, Stats& st) const override {
    return chains_->glint(gl_, o, d, si, st.film_x, st.film_y, rng, st);
  }
  // Why light_trace > 0 runs no light tracer ("" when it runs or was not asked)
  const std::string& light_trace_off() const { return lt_off_; }
  bool chains_active() const { return chains_ != nullptr; }
  // a point or spot chain light: rate 0 would lose its light (ChainEstimator::has_delta_lights)
  bool chains_delta_lights() const { return chains_ && chains_->has_delta_lights(); }
  const ChainEstimator* chains() const { return chains_.get(); }
  PathParams::CameraDelta camera_delta() const { return p_.camera_delta; }
  Color Li_hit(const Scene& scene, const Vec3& o, const Vec3& d, SurfaceInteraction si, PCG32& rng,
               Stats& stats) const override {
    return trace(scene, o, d, std::move(si), rng, stats, p_.camera_delta);
  }
  Color Li_delta(const Scene& scene, const Vec3& o, const Vec3& d, float tmin, float tmax, PCG32& rng,
                 Stats& stats, bool branch) const override {
    stats.rays++;
    if (branch && p_.delta_branch > 0)
      return delta_tree(scene, scene.intersect(o, d, tmin, tmax), d, Color(1.f), 0, 1.f, p_.delta_branch, rng,
                        stats);
    return trace(scene, o, d, scene.intersect(o, d, tmin, tmax), rng, stats, PathParams::CameraDelta::Only);
  }
  bool delta_branched() const override { return p_.delta_branch > 0; }
  bool delta_split_sobol() const override { return p_.delta_split_sobol; }

 private:
  Color trace(const Scene& scene, const Vec3& o, const Vec3& d, SurfaceInteraction si, PCG32& rng,
              Stats& stats, PathParams::CameraDelta mode) const;
  // Whether a path at vertex `depth` may scatter again: not at max_depth
  // (segments, -1 unbounded) nor past the safety cap (counted).
  bool may_scatter(uint32_t depth, Stats& st) const {
    if (depth + 1 >= uint32_t(p_.max_depth)) return false;
    if (int(depth) >= p_.hard_depth_cap) {
      st.depth_capped++;
      return false;
    }
    return true;
  }
  // Russian roulette (Mitsuba 3's rule) at the path's new depth, decided
  // before the ray is traced (a path it ends costs no intersection); draws one
  // variate unless beta is black. false: the path ends. p_rr: multiplied by
  // the survival probability where the roulette ran.
  bool survives_roulette(Color& beta, float eta, uint32_t depth, PCG32& rng, double* p_rr = nullptr) const {
    const float bmax = max_comp(beta);
    if (!(bmax > 0.f)) return false;
    const float q = std::min(bmax * eta * eta, 0.95f);
    const float u_rr = rng.next_float();
    if (int(depth) >= p_.rr_depth) {
      if (u_rr >= q) return false;
      beta /= q;
      if (p_rr) *p_rr *= double(q);
    }
    return true;
  }
  // The probability that this roulette lets a path through the chain of
  // `d` (ChainEstimator::PathDensities) from a separator at `depth` with
  // throughput beta and eta there: the roulettes after the separator's
  // scattering and after each chain vertex's, as trace() runs them.
  double chain_survival(Color beta, float eta, uint32_t depth, const ChainEstimator::PathDensities& d) const {
    double p = 1.0;
    for (int i = 0; i <= d.n; ++i) {
      if (i == 0) beta *= d.sep_weight;
      else {
        beta *= d.w[size_t(i - 1)];
        eta *= d.eta[size_t(i - 1)];
      }
      ++depth;
      if (int(depth) < p_.rr_depth) continue;
      const float q = std::min(max_comp(beta) * eta * eta, 0.95f);
      if (!(q > 0.f)) return 0.0;
      beta /= q;
      p *= double(q);
    }
    return p;
  }
  // trace in Only mode from the hit si of direction d, with branching at the
  // next `levels` two-lobe delta vertices (PathParams::delta_branch).
  Color delta_tree(const Scene& scene, SurfaceInteraction si, Vec3 d, Color beta, uint32_t depth, float eta,
                   int levels, PCG32& rng, Stats& stats, bool glint_prefix = true) const;
  PathParams p_;
  std::shared_ptr<const ChainEstimator> chains_;
  std::shared_ptr<const LightTracer> lt_;   // (holds a reference to *chains_, none in glossy mode)
  std::string lt_off_;
  ChainEstimator::GlintLights gl_;   // (usable() false: no glints)
  // Is a light hit after `depth` vertices, all chain vertices with a delta
  // BSDF (a smooth one: a rough one below the glossy threshold can sample a
  // delta lobe when index-matched, and the glints' seeds stop there) and a
  // delta, not null, lobe, the glints' path? (path.cpp drops it)
  bool glint_path(uint32_t depth, bool glint_prefix, int emitter) const {
    return glints_on() && glint_prefix && depth >= 1 && int(depth) <= gl_.mmax && gl_.owns(emitter);
  }
};

}  // namespace mpg
