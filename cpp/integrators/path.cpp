#include "integrators/path.h"

namespace mpg {

Color PathIntegrator::trace(const Scene& scene, const Vec3& o_in, const Vec3& d_in,
                            SurfaceInteraction si, PCG32& rng, Stats& st,
                            PathParams::CameraDelta mode) const {
  Color L(0.f), beta(1.f);
  if (p_.max_depth == 0) return L;
  float eta = 1.f;
  Vec3 d = d_in;
  Vec3 prev_p = o_in;
  float prev_pdf = 1.f;
  bool prev_delta = true;
  const uint32_t max_depth = uint32_t(p_.max_depth);  // -1 -> unbounded, as Mitsuba 3
  // Specular chain since the last separator (for ownership by the chain estimator).
  uint32_t sep_depth = 0;
  SurfaceInteraction sep_si;
  BSDFContext sep_ctx;
  std::string tau;
  thread_local std::vector<SurfaceInteraction> chain_si;  // the chain's vertices (for the MIS weight)
  chain_si.clear();
  bool chain_ok = false;
  // separators before this vertex; the guided trace of handed-off pixels runs
  // at the first one only (both its sides: the trace and the path tracer's weight)
  uint32_t seps = 0;
  bool sep_first = false;
  Vec3 sep_wo(0.f);   // the separator's BSDF sample direction (omega_D of a chain after it)
  double rr_sep = 1.0;  // the roulette's survival probabilities since it (Stats::sample_tail)
  // ... and whether the tails cover the chain after it (a reflection at the
  // separator, delta chain vertices; the estimator's side, estimate(), the same)
  bool tail_ok = false;
  // every BSDF sample so far delta (PathParams::camera_delta)
  bool delta_prefix = true;
  // ... and every vertex so far a chain vertex (a delta lobe, no null
  // interface): a separator behind them is one the light tracer's photons
  // reach through a camera-side chain (LightTracer::camera_chain_max)
  bool chain_prefix = true;
  // ... and, for the glints, every such vertex's BSDF a delta one (PathIntegrator::glint_path)
  bool glint_prefix = true;
  // The chain rate at a separator: the pixel's, but in a pixel of rate 0
  // (handed to the path tracer) chains_->handoff_deep() at its separators
  // after the first (ChainParams::handoff_deep, or the pixel's
  // PassConfig::deep_rate_map); sep_rate: the last separator's, which the
  // path tracer's share of its chain paths uses
  const float deep_rate = !chains_ ? 0.f : st.pixel_deep_rate >= 0.f ? st.pixel_deep_rate : chains_->handoff_deep();
  auto rate_here = [&]() -> float {
    return st.pixel_chain_rate == 0.f && seps > 0 && deep_rate > 0.f ? deep_rate : st.pixel_chain_rate;
  };
  float sep_rate = st.pixel_chain_rate;
  const int lt_cam = lt_ ? lt_->camera_chain_max() : 0;
  const bool lt_area = lt_ && lt_->traces_area() && !lt_->glossy();
  // Glossy mode of the light tracer (no chain estimator): gl_n counts the
  // caster vertices after the camera's first hit while every vertex since is
  // one (-1: not such a path). Paths camera -> x_D -> 1..gl_max casters -> a
  // traced light are the photons': dropped here, the NEE at the last caster
  // and the BSDF sample that hits the light alike (LightTracer, glossy mode).
  const bool gl = lt_ && lt_->glossy();
  const int gl_max = gl ? lt_->max_chain() : 0;
  int gl_n = -1;
  const bool cd_only = mode == PathParams::CameraDelta::Only;
  const bool cd_exclude = mode == PathParams::CameraDelta::Exclude;
  const bool cd_all = mode == PathParams::CameraDelta::All;
  // A training pass's record of the rate-0 option with the guided trace
  // (Stats::record_trace): in pixels that run chain estimates, where the
  // pass's guided_trace_map does not switch it off
  const bool trace_alt = chains_ && st.record_trace && st.pixel_chain_rate != 0.f && st.pixel_trace_k != 0 &&
                         chains_->guided_trace_on();
  // (the sample records the traces' values whatever its path: a condition of
  // the pass and pixel, so that the recorded samples are a fair subset)
  if (trace_alt) st.sample_trace_recorded = true;
  // The rate-0 pixel's count of guided traces
  const int trace_k = !chains_ ? 0 : (st.pixel_trace_k < 0 ? chains_->handoff_guided() : st.pixel_trace_k);
  // ... a chain path after the first separator: the traces' weight replaces
  // the path tracer alone's 1
  // ... and the forms' second moments of the chain paths (Stats::sample_tail):
  // a chain-path value Y as it enters the sample, times the path's
  // contribution to its form's second moment per unit of its integrand F.
  // With the path tracer's density b, its roulette's survival p after the
  // separator and k traces' density k g (none at k = 0, or where no trace
  // can produce the path), by the balance heuristic b / (b + k g) the path
  // tracer's value is F / (p (b + k g)) with density b p and a trace's
  // F / (b + k g) with k g: together F (b / p + k g) / (b + k g)^2 = num
  // (b / p + k g) / (b + k g)^2, num = F.
  auto tail_add = [&](const Color& Y, const Color& num, double b, double g, double p) {
    if (!trace_alt || is_black(Y) || !(p > 0.0)) return;
    const double y = (double(Y.x) * num.x + double(Y.y) * num.y + double(Y.z) * num.z) / 3.0;   // mean over RGB
    for (int f = 0; f <= Stats::kTraceKs; ++f) {
      const double kg = f == 0 ? 0.0 : double(1 << (f - 1)) * std::max(g, 0.0);
      const double den = b + kg;
      if (den > 0.0) st.sample_tail[f] += y * (b / p + kg) / (den * den);
    }
    st.sample_chain_part += Y;
  };
  // ... a chain path after a separator, found by the path tracer, whose
  // value in the sample is c w_in: after the first separator, the traces'
  // weight replaces the path tracer alone's 1
  auto trace_alt_hit = [&](const SurfaceInteraction& hit, const Color& c, float w_in) {
    if (!trace_alt || !chain_ok || tau.empty() || is_black(c)) return;
    double b = 0.0, g = 0.0;
    bool shared = false;
    if (sep_first) {
      shared = chains_->guided_trace_densities(sep_si, sep_ctx, sep_depth, max_depth, sep_wo,
                                               chain_si.data(), tau, hit, st, b, g);
      // (k = 2^i traces: Stats::kTraceKs)
      for (int i = 0; i < Stats::kTraceKs; ++i)
        st.sample_trace_hits_delta[i] += c * (ChainEstimator::guided_trace_pt_weight(shared, b, g, 1 << i) - 1.f);
      st.sample_trace_hit = true;
    }
    if (!tail_ok) return;
    // (the records' own view of the same: the path's value under each form)
    st.sample_seen_P[0] += c;
    for (int i = 0; i < Stats::kTraceKs; ++i)
      st.sample_seen_P[i + 1] += c * ChainEstimator::guided_trace_pt_weight(shared, b, g, 1 << i);
    // (the path tracer alone's value is c = num / (b p): with b = 1, num = c p)
    tail_add(c * w_in, c * float(rr_sep), 1.0, shared && b > 0.0 ? g / b : 0.0, rr_sep);
  };

  // Light found by BSDF sampling: on a delta prefix (All) it is also the
  // sample's delta part, which a split pixel averages apart (render.cpp).
  auto add = [&](const Color& c) {
    if (cd_all && delta_prefix) {
      st.sample_delta_L += c;
      if (st.split_delta) return;
    }
    L += c;
  };

  for (uint32_t depth = 0;; ) {
    const bool show = !(p_.hide_emitters && depth == 0) && !(cd_exclude && delta_prefix);
    if (!si.valid) {
      if (show) {
        for (int e : scene.infinite_emitters) {
          const Emitter& em = scene.emitters[size_t(e)];
          if (em.type == Emitter::Type::Directional) continue;
          const Color Le = em.eval_env(d);
          if (is_black(Le)) continue;
          const float w = prev_delta ? 1.f : power_heuristic(prev_pdf, scene.pdf_emitter_escape(e, d));
          add(beta * Le * w);
        }
      }
      break;
    }
    st.path_vertices++;
    const Shape& shape = scene.shapes[size_t(si.shape)];
    if (shape.emitter >= 0 && show) {
      const Color Le = scene.emitted(si);
      // (rate 0: this pixel's chain light is the path tracer's alone, below)
      LeafQuery leaf;  // (active_for's lookup, which pt_weight reuses)
      if (glint_path(depth, glint_prefix, shape.emitter)) {
        // camera -> chain vertices -> a small light: the glints bring this path
        if (!is_black(Le)) st.glint_pt_dropped++;
      } else if (gl && gl_n >= 1 && gl_n <= gl_max && lt_->traces_emitter(shape.emitter)) {
        // the glossy casters' photons bring this path
        if (!is_black(Le)) st.lt_pt_dropped++;
      } else if (lt_area && sep_depth == 0 && chain_ok && !tau.empty() && lt_->traces_emitter(shape.emitter) &&
          chains_->owns(sep_depth, max_depth, tau)) {
        // the light tracer's photons bring this path: the last separator the
        // camera's first hit, whose chains to area lights are the photons'
        // (LightTracer::traces_area: seen directly only)
        if (!is_black(Le)) st.lt_pt_dropped++;
      } else if (chains_ && chain_ok && !tau.empty() && sep_rate != 0.f &&
          chains_->owns(sep_depth, max_depth, tau) && chains_->active_for(sep_si.p, si.p, tau, &st, &leaf)) {
        // A path the chain estimator also produces: this side's share of it
        // (0 when the estimator takes it whole; design.md "No double counting").
        if (!is_black(Le)) {
          bool whole = false;   // (record_classes: a light or length the estimator never produces)
          // (the rate its separator ran the estimator at, which rate_b reads)
          const float pixel_rate = st.pixel_chain_rate;
          st.pixel_chain_rate = sep_rate;
          const float w = chains_->pt_weight(sep_si, sep_ctx, sep_depth, max_depth, chain_si.data(), tau, si,
                                             rng, st, beta * Le, &leaf, &whole);
          st.pixel_chain_rate = pixel_rate;
          st.sample_alt_delta += beta * Le * (1.f - w);  // the path tracer alone keeps it whole
          st.sample_owned_hit = true;  // (w can round to 1 where the path tracer's density dominates)
          trace_alt_hit(si, beta * Le, w);
          if (w > 0.f) {
            L += beta * Le * w;
            st.add_class(whole ? Stats::kClassUnowned : Stats::kClassShared, beta * Le * w);
            st.owned_shared++;
          } else {
            st.owned_dropped++;
          }
        }
      } else if (chains_ && chain_ok && !tau.empty() && sep_first && sep_rate == 0.f &&
                 trace_k > 0 && chains_->guided_trace_on()) {
        // A handed-off pixel's chain path: shared with the guided trace by the
        // balance heuristic (ChainEstimator::guided_trace)
        if (!is_black(Le)) {
          double b = 0.0, g = 0.0;
          const bool shared = chains_->guided_trace_densities(sep_si, sep_ctx, sep_depth, max_depth, sep_wo,
                                                              chain_si.data(), tau, si, st, b, g);
          const Color v = beta * Le * ChainEstimator::guided_trace_pt_weight(shared, b, g, trace_k);
          L += v;
          st.add_class(Stats::kClassTraced, v);
        }
      } else if (!is_black(Le)) {
        const float w = prev_delta ? 1.f : power_heuristic(prev_pdf, scene.pdf_emitter_hit(prev_p, si));
        add(beta * Le * w);
        if (chain_ok && !tau.empty() && st.record_classes) {
          // why the estimator does not take it (active_for filled `leaf` if it ran)
          const int c = sep_rate == 0.f ? Stats::kClassHanded
                        : !leaf.done                ? Stats::kClassUnowned
                        : leaf.leaf                 ? Stats::kClassUnseen
                                                    : Stats::kClassInactive;
          st.add_class(c, beta * Le * w);
        }
        // (a chain path here has w = 1: its last vertex is a chain vertex)
        if (prev_delta) trace_alt_hit(si, beta * Le, w);
      }
    }
    if (!may_scatter(depth, st)) break;
    const BSDFContext ctx = scene.bsdfs.resolve(shape.bsdf, si);
    if (!ctx.leaf) break;

    // A chain vertex (smooth, or glossy below the threshold, when a chain
    // estimator runs) is not a separator: no NEE there, its light is the chains'.
    const bool chain_vertex = chains_ && chains_->is_chain_bsdf(*ctx.leaf) && chains_->is_chain_shape(si.shape);
    const bool separator = !ctx.leaf->is_delta() && !chain_vertex;
    if (gl) {
      const bool caster = lt_->caster_vertex(si.shape, *ctx.leaf);
      if (depth == 0) gl_n = !ctx.leaf->is_delta() && !caster ? 0 : -1;
      else if (gl_n >= 0) gl_n = caster ? gl_n + 1 : -1;
    }
    // Next-event estimation (not for delta BSDFs).
    const float u_sel = rng.next_float();
    const Vec2 u_em(rng.next_float(), rng.next_float());
    if (separator && !cd_only) {
      const EmitterSample es = scene.sample_emitter(si.p, u_sel, u_em);
      if (gl && gl_n >= 1 && gl_n <= gl_max && lt_->traces_emitter(es.emitter)) {
        // (a glossy caster's NEE to a traced light: the photons' path)
        if (es.pdf > 0.f && !is_black(es.value)) st.lt_pt_dropped++;
      } else if (es.pdf > 0.f && !is_black(es.value)) {
        const Color f = scene.bsdfs.eval(ctx, si.wi, es.wi);
        if (!is_black(f)) {
          // (to the light's point itself, Scene::occluded_to; an infinite
          // light along es.wi)
          st.shadow_rays++;
          const bool blocked = std::isinf(es.dist)
                                   ? scene.occluded(offset_ray_origin(si.p, si.ng, es.wi), es.wi, 0.f, kInf)
                                   : scene.occluded_to(si.p, si.ng, es.p);
          if (!blocked) {
            const float w = es.delta ? 1.f : power_heuristic(es.pdf, scene.bsdfs.pdf(ctx, si.wi, es.wi));
            L += beta * f * es.value * (w / es.pdf);
          }
        }
      }
    }

    // Light through specular chains, estimated at the separator.
    if (chains_ && separator && !cd_only) {
      // Russian roulette on the (costly) chain estimate: E[1{u < q} X / q] = E[X]
      // for any q > 0, and the path tracer's share of the chain paths does not
      // depend on whether the estimator ran (with mis_rate it depends on q, the
      // pixel's fixed rate, as the estimator's X does), so the sum stays unbiased.
      // (q = 1 draws no variate: sms/sms_star images are unchanged.)
      // q is the pixel's rate when the pass has a map (mpg's learned rates),
      // the estimator's otherwise. q = 0: the pixel's chain light is the path
      // tracer's whole (above); the same for every sample of the pixel, so
      // each path is counted once.
      // (the estimator reads the rate from st: rate_here's for this separator)
      const float pixel_rate = st.pixel_chain_rate;
      st.pixel_chain_rate = rate_here();
      if (pixel_rate == 0.f && st.pixel_chain_rate > 0.f) st.chain_deep++;
      const float q = chains_->rate_at(st);
      // the camera's first hit, whose area-light chains are the photons'
      const bool lt_first = lt_area && depth == 0;
      if (q <= 0.f) {
        st.chain_handed++;
        // (not at the camera's first hit when the photons take the area
        // lights' chains: the trace's types are all owned there, mpg's mode
        // owning every type up to nmax)
        if (seps == 0 && trace_k > 0 && chains_->guided_trace_on() &&
            !lt_first) {
          const Color v = beta * chains_->guided_trace(si, ctx, depth, max_depth, trace_k, rng, st);
          L += v;
          st.add_class(Stats::kClassTraced, v);
        }
      } else if (q >= 1.f || rng.next_float() < q) {
        ChainEstimator::PathDensities dens;
        dens.want_g = seps == 0;
        // the camera's first hit, or a separator behind at most lt_cam chain
        // vertices: its chains to point/spot lights are the light tracer's
        st.chain_skip_delta_lights = lt_ && (depth == 0 || (chain_prefix && int(depth) <= lt_cam));
        st.chain_skip_area_lights = lt_first;
        const Color X = beta * chains_->estimate(si, ctx, depth, max_depth, rng, st, beta, trace_alt ? &dens : nullptr);
        st.chain_skip_delta_lights = st.chain_skip_area_lights = false;
        L += X * (1.f / q);
        st.add_class(Stats::kClassChain, X * (1.f / q));
        if (dens.ok)
          tail_add(X * (1.f / q), beta * dens.unit, dens.b, dens.g, chain_survival(beta, eta, depth, dens));
        st.sample_alt_delta -= X * (1.f / q);
        // (a non-finite X rejects the whole sample, render.cpp: not counted here)
        const double m2 = (double(X.x) * X.x + double(X.y) * X.y + double(X.z) * X.z) / (3.0 * double(q));
        if (std::isfinite(m2)) st.pixel_chain_m2 += m2;
      } else {
        st.chain_skipped++;
      }
      // (not where the render runs no trace: a first hit whose area-light
      // chains are the photons'; the sample records 0 there, as the render has)
      if (trace_alt && seps == 0 && !lt_first) {
        // two traces, from which the render worker forms the values of k traces
        const uint64_t r0 = st.rays;
        for (TraceSample& t : st.sample_traces) {
          t = chains_->guided_trace_one(si, ctx, depth, max_depth, rng, st);
          t.f *= beta;
          if (!is_black(t.f)) st.sample_trace_hit = true;
        }
        st.trace_rays += st.rays - r0;
      }
      st.pixel_chain_rate = pixel_rate;
    }

    // BSDF sampling.
    const float u1 = rng.next_float();
    const Vec2 u2(rng.next_float(), rng.next_float());
    Vec3 wo;
    const BSDFSample bs = scene.bsdfs.sample(ctx, si.wi, u1, u2, wo);
    if (!(bs.pdf > 0.f) || is_black(bs.weight)) break;
    if (!bs.delta) {
      if (cd_only) break;  // the rest of this path is Exclude's
      delta_prefix = false;
    }
    chain_prefix = chain_prefix && chain_vertex && bs.delta && !bs.null;
    glint_prefix = chain_prefix && glint_prefix && ctx.leaf->is_delta();
    // (a delta lobe of the camera's first hit, smooth plastic's coating: not
    // in the BSDF the photons' splat evaluates, so such paths stay here)
    if (gl && depth == 0 && bs.delta) gl_n = -1;
    beta *= bs.weight;
    eta *= bs.eta;
    if (chains_) {
      if (separator) {
        sep_depth = depth;
        sep_rate = rate_here();
        sep_first = seps == 0;
        sep_wo = wo;
        rr_sep = 1.0;
        tail_ok = !bs.transmission;
        sep_si = si;
        sep_ctx = ctx;
        tau.clear();
        chain_si.clear();
        // A delta lobe of a separator (smooth plastic's coating, an index-
        // matched interface) is not in the estimator's f_s: those paths are
        // the path tracer's alone.
        chain_ok = !bs.delta;
      } else if (chain_ok) {
        if (chains_->is_chain_shape(si.shape) && !bs.null) {
          tau.push_back(bs.transmission ? 'T' : 'R');
          chain_si.push_back(si);
          tail_ok = tail_ok && bs.delta && tau.size() <= size_t(ChainDistribution::kMaxN);
        } else {
          chain_ok = false;
        }
      }
    }
    if (separator) ++seps;
    prev_p = si.p;
    prev_pdf = bs.pdf;
    prev_delta = bs.delta || chain_vertex;

    ++depth;

    if (!survives_roulette(beta, eta, depth, rng, &rr_sep)) break;
    const Vec3 org = offset_ray_origin(si.p, si.ng, wo);
    d = wo;
    st.rays++;
    if (cd_all && delta_prefix) st.delta_prefix_rays++;
    si = scene.intersect(org, d, 0.f, kInf);
  }
  return L;
}

// The light seen from the camera through delta scattering only, as trace()
// in Only mode, except at the first `levels` delta vertices whose BSDF has two
// delta lobes (a dielectric's reflection and refraction, Fresnel F and 1 - F):
// there both lobes are followed, each with beta * weight * probability, the
// expectation over the lobe choice taken exactly (trace() draws one lobe with
// its probability and weighs it by weight alone). Term by term the same
// expected value; the variance of the choice (a glint seen by reflection with
// probability F ~ 0.05 is L w.p. F: variance ~ L^2 F) is gone, and what is left
// is the pixel footprint's. A one-lobe delta BSDF (a mirror, total internal
// reflection, a null interface) continues as in trace(). Recursion depth is at
// most `levels` (<= 8: at most 2^8 leaves).
Color PathIntegrator::delta_tree(const Scene& scene, SurfaceInteraction si, Vec3 d, Color beta, uint32_t depth,
                                 float eta, int levels, PCG32& rng, Stats& st, bool glint_prefix) const {
  Color L(0.f);
  if (p_.max_depth == 0) return L;
  for (;;) {
    const bool show = !(p_.hide_emitters && depth == 0);
    if (!si.valid) {
      if (show) {
        for (int e : scene.infinite_emitters) {
          const Emitter& em = scene.emitters[size_t(e)];
          if (em.type == Emitter::Type::Directional) continue;
          const Color Le = em.eval_env(d);
          if (!is_black(Le)) L += beta * Le;  // (a delta prefix: weight 1, as in trace)
        }
      }
      break;
    }
    st.path_vertices++;
    const Shape& shape = scene.shapes[size_t(si.shape)];
    if (shape.emitter >= 0 && show) {
      // (no separator on a delta prefix: never a chain path, as in trace;
      // the glints' paths are dropped, as there)
      const Color Le = scene.emitted(si);
      if (glint_path(depth, glint_prefix, shape.emitter)) {
        if (!is_black(Le)) st.glint_pt_dropped++;
      } else if (!is_black(Le)) {
        L += beta * Le;
      }
    }
    if (!may_scatter(depth, st)) break;
    const BSDFContext ctx = scene.bsdfs.resolve(shape.bsdf, si);
    if (!ctx.leaf) break;
    const Vec2 u2(rng.next_float(), rng.next_float());
    Vec3 wo;
    BSDFSample bs;
    // (as trace's glint_prefix: a chain vertex with a delta BSDF, a delta lobe, not null)
    const bool chain_vertex = chains_ && chains_->is_chain_bsdf(*ctx.leaf) && chains_->is_chain_shape(si.shape) &&
                              ctx.leaf->is_delta();
    if (levels > 0 && ctx.leaf->is_delta()) {
      // u1 = 0 selects the first lobe (reflection: u1 <= F), u1 = 1 the second
      // (refraction, unless F = 1); distinct lobes: branch.
      Vec3 wo_r, wo_t;
      const BSDFSample r = scene.bsdfs.sample(ctx, si.wi, 0.f, u2, wo_r);
      const BSDFSample t = scene.bsdfs.sample(ctx, si.wi, 1.f, u2, wo_t);
      const bool ok_r = r.pdf > 0.f && r.delta && !is_black(r.weight);
      const bool ok_t = t.pdf > 0.f && t.delta && !is_black(t.weight);
      if (ok_r && ok_t && (r.transmission != t.transmission || r.null != t.null)) {
        st.delta_branches++;
        // the refracted branch by recursion, the reflected one by this loop
        const Vec3 org_t = offset_ray_origin(si.p, si.ng, wo_t);
        st.rays++;
        L += delta_tree(scene, scene.intersect(org_t, wo_t, 0.f, kInf), wo_t, beta * t.weight * t.pdf,
                        depth + 1, eta * t.eta, levels - 1, rng, st, glint_prefix && chain_vertex && !t.null);
        bs = r;
        bs.weight = r.weight * r.pdf;
        wo = wo_r;
        --levels;
      } else {
        bs = scene.bsdfs.sample(ctx, si.wi, rng.next_float(), u2, wo);
      }
    } else {
      bs = scene.bsdfs.sample(ctx, si.wi, rng.next_float(), u2, wo);
    }
    if (!(bs.pdf > 0.f) || is_black(bs.weight) || !bs.delta) break;  // Only: ends at a non-delta vertex
    glint_prefix = glint_prefix && chain_vertex && !bs.null;
    beta *= bs.weight;
    eta *= bs.eta;
    ++depth;
    // Russian roulette as trace's (unbiased either way; it bounds the tails' cost)
    if (!survives_roulette(beta, eta, depth, rng)) break;
    const Vec3 org = offset_ray_origin(si.p, si.ng, wo);
    d = wo;
    st.rays++;
    si = scene.intersect(org, d, 0.f, kInf);
  }
  return L;
}

}  // namespace mpg
