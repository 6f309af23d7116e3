// Python bindings: scene construction from numpy arrays and dicts, render
// jobs that run with the GIL released, and test entry points for warps/BSDFs.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <chrono>
#include <memory>
#include <stdexcept>

#include "core/rng.h"
#include "core/warp.h"
#include "integrators/path.h"
#include "manifold/chain_estimator.h"
#include "manifold/walk.h"
#include "guiding/guiding_state.h"
#include "render/render.h"
#include "scene/fresnel.h"
#include "scene/scene.h"

namespace py = pybind11;
using namespace mpg;

// Sub-path samples of a training pass, kept in C++ until the next STree build.
struct SubpathBuffer {
  std::vector<mpg::SubpathSample> v;
};

namespace {

using FArray = py::array_t<float, py::array::c_style | py::array::forcecast>;
using DArray = py::array_t<double, py::array::c_style | py::array::forcecast>;
using UArray = py::array_t<uint32_t, py::array::c_style | py::array::forcecast>;

Vec3 vec3(const py::handle& h) {
  auto a = py::cast<std::vector<float>>(h);
  if (a.size() == 1) return Vec3(a[0]);
  if (a.size() != 3) throw std::invalid_argument("expected 3 components");
  return Vec3(a[0], a[1], a[2]);
}

Mat4 mat4(const py::handle& h) {
  DArray a = py::cast<DArray>(h);
  if (a.ndim() != 2 || a.shape(0) != 4 || a.shape(1) != 4) throw std::invalid_argument("expected a 4x4 matrix");
  Mat4 m;
  auto r = a.unchecked<2>();
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) m[j][i] = float(r(i, j));  // glm is column-major
  return m;
}

Mat3 mat3(const py::handle& h) {
  DArray a = py::cast<DArray>(h);
  if (a.ndim() != 2 || a.shape(0) != 3 || a.shape(1) != 3) throw std::invalid_argument("expected a 3x3 matrix");
  Mat3 m;
  auto r = a.unchecked<2>();
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) m[j][i] = float(r(i, j));
  return m;
}

template <typename T>
T get(const py::dict& d, const char* k, T def) {
  return d.contains(k) ? py::cast<T>(d[k]) : def;
}

std::vector<Vec3> rows3(const FArray& a, const char* what) {
  if (a.ndim() != 2 || a.shape(1) != 3) throw std::invalid_argument(std::string(what) + " must have shape (N, 3)");
  std::vector<Vec3> v(size_t(a.shape(0)));
  auto r = a.unchecked<2>();
  for (ssize_t i = 0; i < a.shape(0); ++i) v[size_t(i)] = Vec3(r(i, 0), r(i, 1), r(i, 2));
  return v;
}

int add_texture_bitmap(Scene& s, const FArray& img, const py::object& to_uv, bool bilinear, const std::string& wrap) {
  if (img.ndim() != 3 || img.shape(2) != 3) throw std::invalid_argument("bitmap must have shape (H, W, 3)");
  Texture t;
  t.kind = Texture::Kind::Bitmap;
  t.height = int(img.shape(0));
  t.width = int(img.shape(1));
  if (t.width < 1 || t.height < 1) throw std::invalid_argument("empty bitmap");
  t.data.assign(img.data(), img.data() + img.size());
  t.to_uv = mat3(to_uv);
  t.bilinear = bilinear;
  t.wrap = wrap == "clamp" ? Texture::Wrap::Clamp : wrap == "mirror" ? Texture::Wrap::Mirror : Texture::Wrap::Repeat;
  s.bsdfs.textures.push_back(std::move(t));
  return int(s.bsdfs.textures.size()) - 1;
}

int add_bsdf(Scene& s, const std::string& type, const py::dict& p) {
  BSDF b;
  static const std::map<std::string, BSDFType> types = {
      {"diffuse", BSDFType::Diffuse},       {"conductor", BSDFType::Conductor},
      {"roughconductor", BSDFType::RoughConductor}, {"dielectric", BSDFType::Dielectric},
      {"roughdielectric", BSDFType::RoughDielectric}, {"thindielectric", BSDFType::ThinDielectric},
      {"plastic", BSDFType::Plastic},       {"twosided", BSDFType::TwoSided},
      {"normalmap", BSDFType::NormalMap},   {"null", BSDFType::Null}};
  auto it = types.find(type);
  if (it == types.end()) throw std::invalid_argument("unknown BSDF type '" + type + "'");
  b.type = it->second;
  b.reflectance = get<int>(p, "reflectance", -1);
  b.specular_reflectance = get<int>(p, "specular_reflectance", -1);
  b.specular_transmittance = get<int>(p, "specular_transmittance", -1);
  if (p.contains("eta")) b.eta_c = vec3(p["eta"]);
  if (p.contains("k")) b.k_c = vec3(p["k"]);
  const float int_ior = get<float>(p, "int_ior", 1.5046f), ext_ior = get<float>(p, "ext_ior", 1.000277f);
  if (!(int_ior > 0.f) || !(ext_ior > 0.f)) throw std::invalid_argument("index of refraction must be positive");
  b.eta = int_ior / ext_ior;
  b.mf.type = get<std::string>(p, "distribution", "beckmann") == "ggx" ? MicrofacetType::GGX : MicrofacetType::Beckmann;
  const float alpha = get<float>(p, "alpha", 0.1f);
  b.mf.ax = std::max(1e-4f, get<float>(p, "alpha_u", alpha));
  b.mf.ay = std::max(1e-4f, get<float>(p, "alpha_v", alpha));
  b.mf.sample_visible = get<bool>(p, "sample_visible", true);
  b.nonlinear = get<bool>(p, "nonlinear", false);
  b.front = get<int>(p, "front", -1);
  b.back = get<int>(p, "back", -1);
  b.nested = get<int>(p, "nested", -1);
  b.normalmap = get<int>(p, "normalmap", -1);
  const int ntex = int(s.bsdfs.textures.size()), nb = int(s.bsdfs.nodes.size());
  for (int t : {b.reflectance, b.specular_reflectance, b.specular_transmittance, b.normalmap})
    if (t >= ntex) throw std::invalid_argument("texture id out of range");
  for (int c : {b.front, b.back, b.nested})
    if (c >= nb) throw std::invalid_argument("child BSDF id out of range");
  if (b.type == BSDFType::TwoSided && (b.front < 0 || b.back < 0)) throw std::invalid_argument("twosided needs children");
  if (b.type == BSDFType::NormalMap && (b.nested < 0 || b.normalmap < 0)) throw std::invalid_argument("normalmap needs a BSDF and a texture");
  if (b.type == BSDFType::Plastic) {
    b.fdr_int = fresnel_diffuse_reflectance(1.f / b.eta);
    const float d_mean = b.reflectance >= 0 ? s.bsdfs.textures[size_t(b.reflectance)].mean_value() : 0.5f;
    const float s_mean = b.specular_reflectance >= 0 ? s.bsdfs.textures[size_t(b.specular_reflectance)].mean_value() : 1.f;
    b.specular_sampling_weight = s_mean / std::max(1e-6f, d_mean + s_mean);
  }
  s.bsdfs.nodes.push_back(b);
  return nb;
}

void check_not_committed(const Scene& s) {
  if (s.committed()) throw std::runtime_error("scene already committed");
}

// The pass's arrays are views of the job's own buffers (`base`, the Python
// RenderJob, is kept alive by them): a training pass that records its costs
// returns ~40 MB at 256 x 256, whose copy (and the fresh pages' faults) took
// 20 ms a pass, a tenth of a 2 s render's training.
py::dict pass_to_dict(PassResult& r, py::handle base) {
  py::dict out;
  const std::vector<ssize_t> rgb = {r.height, r.width, 3}, grey = {r.height, r.width};
  auto put = [&](const char* key, const std::vector<double>& v, const std::vector<ssize_t>& shape) {
    ssize_t n = 1;
    for (ssize_t e : shape) n *= e;
    if (ssize_t(v.size()) != n) throw std::logic_error(std::string("pass result ") + key + " has the wrong size");
    out[key] = DArray(shape, v.data(), base);
  };
  put("sum", r.sum, rgb);
  put("sum_sq", r.sum_sq, rgb);
  out["spp"] = r.spp;
  out["seconds"] = r.seconds;
  out["cancelled"] = r.cancelled;
  if (!r.chain_m2.empty()) {   // PassConfig::record_costs
    put("chain_m2", r.chain_m2, grey);
    put("chain_steps", r.chain_steps, grey);
    put("walk_steps", r.walk_steps, grey);
    put("rays", r.rays, grey);
    put("alt_sum", r.alt_sum, rgb);
    put("alt_sum_sq", r.alt_sum_sq, rgb);
    put("alt_hits", r.alt_hits, grey);
    put("delta_rays", r.delta_rays, grey);
    // (k = 2^f traces; the tails' and records' index 0 is the path tracer alone)
    put("trace_tail0", r.trace_tail[0], grey);
    put("trace_seen0", r.trace_seen[0], grey);
    for (int f = 0; f < Stats::kTraceKs; ++f) {
      const std::string k = "trace" + std::to_string(1 << f);
      put((k + "_sum").c_str(), r.trace_sum[f], rgb);
      put((k + "_sum_sq").c_str(), r.trace_sum_sq[f], rgb);
      put((k + "_var").c_str(), r.trace_var[f], grey);
      put((k + "_tail").c_str(), r.trace_tail[f + 1], grey);
      put((k + "_seen").c_str(), r.trace_seen[f + 1], grey);
    }
    put("trace_chain_sum", r.trace_chain_sum, rgb);
    put("trace_hits", r.trace_hits, grey);
    put("trace_n", r.trace_n, grey);
    put("trace_lobes", r.trace_lobes, grey);
    put("trace_pt_lobes", r.trace_pt_lobes, grey);
    put("trace_rays", r.trace_rays, grey);
    put("bdelta_n", r.bdelta_n, grey);
    put("bdelta_rays", r.bdelta_rays, grey);
    put("bdelta_within", r.bdelta_within, grey);
    put("udelta_within", r.udelta_within, grey);
  }
  if (!r.delta_sum.empty()) {   // PassConfig::record_costs or record_delta
    put("delta_sum", r.delta_sum, rgb);
    put("delta_sum_sq", r.delta_sum_sq, rgb);
  }
  if (!r.split_path_n.empty()) {   // PassConfig::record_delta (the render's passes)
    put("split_path_sum", r.split_path_sum, rgb);
    put("split_path_sum_sq", r.split_path_sum_sq, rgb);
    put("split_path_n", r.split_path_n, grey);
    put("split_path_rays", r.split_path_rays, grey);
  }
  out["lt_photons"] = r.lt_photons;
  out["lt_work_rays"] = r.lt_work_rays;
  out["lt_work_walk_steps"] = r.lt_work_walk_steps;
  if (r.lt_photons > 0) {   // the light tracer's splats (Integrator::light_tracer)
    put("lt_sum", r.lt_sum, rgb);
    put("lt_sum_sq", r.lt_sum_sq, rgb);
  }
  if (!r.class_sum.empty()) {   // PassConfig::record_classes
    const std::vector<ssize_t> cls = {r.height, r.width, Stats::kClasses};
    put("class_sum", r.class_sum, cls);
    put("class_sum_sq", r.class_sum_sq, cls);
  }
  auto st = r.stats.to_map();
  for (size_t i = 1; i < r.stats.walk_failures.size(); ++i)
    st[std::string("walk_fail_") + walk_failure_name(WalkFailure(i))] = double(r.stats.walk_failures[i]);
  out["stats"] = st;
  auto buf = std::make_shared<SubpathBuffer>();
  buf->v = std::move(r.stats.subpaths);
  out["subpaths"] = buf;
  return out;
}

// A per-pixel map for a render pass (crop height x width floats), copied.
std::shared_ptr<std::vector<float>> pixel_map(const py::object& o, const Camera& c, const char* name) {
  const FArray a = py::cast<FArray>(o);
  if (a.ndim() != 2 || a.shape(0) != c.crop_h || a.shape(1) != c.crop_w)
    throw std::invalid_argument(std::string(name) + " must have shape (crop height, crop width)");
  return std::make_shared<std::vector<float>>(a.data(), a.data() + a.size());
}

// A per-pixel count map (the splits): integers in [1, 64].
std::shared_ptr<std::vector<float>> count_map(const py::object& o, const Camera& c, const char* name) {
  auto m = pixel_map(o, c, name);
  for (float k : *m)
    if (!(k >= 1.f && k <= 64.f && k == std::floor(k)))
      throw std::invalid_argument(std::string(name) + " values must be integers in [1, 64]");
  return m;
}

WalkConfig walk_config(const py::dict& p);

GuideConfig guide_config(float c, float epsilon, int max_depth, int threads, const std::string& filter,
                         int threshold, const std::string& structure, int knn_k, float anchor) {
  GuideConfig cfg;
  cfg.stree.c = c;
  cfg.stree.epsilon = epsilon;
  cfg.stree.max_depth = max_depth;
  cfg.stree.threads = std::max(1, threads);
  cfg.stree.filter = parse_stree_filter(filter);
  cfg.stree.threshold = threshold;
  cfg.structure = parse_guide_structure(structure);
  cfg.knn_k = knn_k;
  cfg.anchor = anchor;
  return cfg;  // ranges are checked by GuidingState::build
}

// mpg's default photons per camera sample (docs/results.md, "Light tracing
// the point lights' caustics")
constexpr float kMpgLightTrace = 0.25f;
constexpr bool kMpgLightTraceThrough = true;
constexpr bool kMpgLightTraceArea = true;
// ... and in glossy mode, where the photons are the caustics' only estimator
// (docs/results.md, "Glossy casters' photons": 0.25 / 0.5 / 1 on plane)
constexpr float kMpgLightTraceGlossy = 0.5f;
// ... and its glints: lights under this many pixels across (docs/results.md, "Glints")
constexpr float kMpgGlints = 2.f;

std::shared_ptr<Integrator> make_integrator(std::shared_ptr<const Scene> scene, const std::string& type,
                                            const py::dict& p) {
  PathParams pp;
  pp.max_depth = get<int>(p, "max_depth", -1);
  pp.rr_depth = get<int>(p, "rr_depth", 5);
  pp.hide_emitters = get<bool>(p, "hide_emitters", false);
  const std::string cd = get<std::string>(p, "camera_delta", "all");
  if (cd == "all") pp.camera_delta = PathParams::CameraDelta::All;
  else if (cd == "exclude") pp.camera_delta = PathParams::CameraDelta::Exclude;
  else if (cd == "only") pp.camera_delta = PathParams::CameraDelta::Only;
  else throw std::invalid_argument("camera_delta must be all, exclude or only, got '" + cd + "'");
  if (pp.max_depth < -1) throw std::invalid_argument("max_depth must be -1 or >= 0");
  if (pp.rr_depth < 0) throw std::invalid_argument("rr_depth must be >= 0");
  pp.delta_branch = get<int>(p, "delta_branch", 0);
  if (pp.delta_branch < 0 || pp.delta_branch > 8)
    throw std::invalid_argument("delta_branch must be in [0, 8], got " + std::to_string(pp.delta_branch));
  pp.delta_split_sobol = get<bool>(p, "delta_split_sobol", false);
  // photons per camera sample (chain integrators; mpg light traces by default)
  pp.light_trace = get<float>(p, "light_trace", type == "mpg" ? kMpgLightTrace : 0.f);
  pp.light_trace_through = get<bool>(p, "light_trace_through", type == "mpg" ? kMpgLightTraceThrough : false);
  pp.light_trace_area = get<bool>(p, "light_trace_area", type == "mpg" ? kMpgLightTraceArea : false);
  pp.light_trace_glossy = get<float>(p, "light_trace_glossy", type == "mpg" ? kMpgLightTraceGlossy : 0.f);
  if (!(pp.light_trace_glossy >= 0.f && pp.light_trace_glossy <= 64.f))
    throw std::invalid_argument("light_trace_glossy must be in [0, 64] photons per camera sample, got " +
                                std::to_string(pp.light_trace_glossy));
  pp.glints = get<float>(p, "glints", type == "mpg" ? kMpgGlints : 0.f);
  if (!(pp.glints >= 0.f && pp.glints <= 1e6f))
    throw std::invalid_argument("glints must be >= 0 (the largest light, in pixels, whose glints are walked; 0: off), got " +
                                std::to_string(pp.glints));
  if (!(pp.light_trace >= 0.f && pp.light_trace <= 64.f))
    throw std::invalid_argument("light_trace must be in [0, 64] photons per camera sample, got " +
                                std::to_string(pp.light_trace));
  if (type == "path") return std::make_shared<PathIntegrator>(pp);
  if (type == "sms" || type == "sms_star" || type == "mpg") {
    if (!scene || !scene->committed()) throw std::runtime_error("scene not committed");
    ChainParams cp;
    cp.mode = type == "sms" ? ChainParams::Mode::Sms : ChainParams::Mode::SmsStar;
    if (type == "mpg") {
      if (p.contains("guide") && !p["guide"].is_none())
        cp.guide = py::cast<std::shared_ptr<GuidingState>>(p["guide"]);
      cp.guide_fraction = get<float>(p, "guide_fraction", cp.guide_fraction);
      cp.selective = get<bool>(p, "selective", cp.selective);
      cp.known_types = get<bool>(p, "known_types", cp.known_types);
      cp.handoff_guided = get<int>(p, "handoff_guided", cp.handoff_guided);
      if (cp.handoff_guided < 0 || cp.handoff_guided > 64) throw std::invalid_argument("handoff_guided must be in 0..64");
      cp.trace_defensive = get<float>(p, "trace_defensive", cp.trace_defensive);
      if (!(cp.trace_defensive >= 0.f && cp.trace_defensive < 1.f))
        throw std::invalid_argument("trace_defensive must be in [0, 1), got " + std::to_string(cp.trace_defensive));
      cp.trace_defensive_kappa = get<float>(p, "trace_defensive_kappa", cp.trace_defensive_kappa);
      if (!(cp.trace_defensive_kappa >= 1e-3f && cp.trace_defensive_kappa <= 1e8f))
        throw std::invalid_argument("trace_defensive_kappa must be in [0.001, 1e8], got " +
                                    std::to_string(cp.trace_defensive_kappa));
      cp.handoff_deep = get<float>(p, "handoff_deep", cp.handoff_deep);
      if (!(cp.handoff_deep == 0.f || (cp.handoff_deep >= 1e-3f && cp.handoff_deep <= 1.f)))
        throw std::invalid_argument("handoff_deep must be 0 (off) or a chain rate in [0.001, 1], got " +
                                    std::to_string(cp.handoff_deep));
      cp.record = get<bool>(p, "record", false);
      cp.guide_n = get<bool>(p, "guide_n", true);
      cp.guide_tau = get<bool>(p, "guide_tau", true);
      cp.guide_dir = get<bool>(p, "guide_dir", true);
      cp.product = get<bool>(p, "product", false);
      if (!(cp.guide_fraction >= 0.f && cp.guide_fraction < 1.f))
        throw std::invalid_argument("guide_fraction must be in [0, 1)");
    }
    // the estimates under each line-search limit (Stats::limit_m2; mpg's training)
    cp.count_limits = get<bool>(p, "count_limits", false);
    cp.tau = get<std::string>(p, "tau", "TT");
    for (char c : cp.tau)
      if (c != 'R' && c != 'T') throw std::invalid_argument("tau must be a string of R and T");
    cp.max_chain = get<int>(p, "max_chain", cp.max_chain);
    cp.continuation = get<float>(p, "continuation", cp.continuation);
    cp.uniqueness_threshold = get<double>(p, "uniqueness_threshold", cp.uniqueness_threshold);
    cp.max_trials = get<int>(p, "max_trials", cp.max_trials);
    cp.mis = get<bool>(p, "mis", cp.mis);
    cp.mis_rate = get<bool>(p, "mis_rate", cp.mis_rate);
    // mpg runs the estimator at 1/8 of the separators by default (measured:
    // docs/results.md, "Chain estimates by roulette"); sms and sms_star keep the
    // papers' every-separator rule unless asked.
    cp.chain_rate = get<float>(p, "chain_rate", type == "mpg" ? 0.125f : 1.0f);
    // >= 1e-3: far above the uniform variate's resolution (2^-24), so the
    // roulette's probability is q, and 1/q stays finite
    if (!(cp.chain_rate >= 1e-3f && cp.chain_rate <= 1.f)) throw std::invalid_argument("chain_rate must be in [0.001, 1]");
    cp.walk = walk_config(p);
    if (cp.max_chain < 1) throw std::invalid_argument("max_chain must be >= 1");
    if (!(cp.continuation >= 0.f && cp.continuation < 1.f)) throw std::invalid_argument("continuation must be in [0, 1)");
    if (cp.max_trials < 1) throw std::invalid_argument("max_trials must be >= 1");
    return std::make_shared<PathIntegrator>(pp, std::make_shared<ChainEstimator>(*scene, cp));
  }
  throw std::invalid_argument("unknown integrator '" + type + "'");
}

// --- test entry points --------------------------------------------------------

FArray warp_sample(const std::string& name, const FArray& u, float param) {
  if (u.ndim() != 2 || u.shape(1) != 2) throw std::invalid_argument("u must have shape (N, 2)");
  const ssize_t n = u.shape(0);
  FArray out(std::vector<ssize_t>{n, 3});
  auto r = u.unchecked<2>();
  auto w = out.mutable_unchecked<2>();
  for (ssize_t i = 0; i < n; ++i) {
    const Vec2 s(r(i, 0), r(i, 1));
    Vec3 v;
    if (name == "uniform_sphere") v = warp::square_to_uniform_sphere(s);
    else if (name == "uniform_hemisphere") v = warp::square_to_uniform_hemisphere(s);
    else if (name == "cosine_hemisphere") v = warp::square_to_cosine_hemisphere(s);
    else if (name == "uniform_cone") v = warp::square_to_uniform_cone(s, param);
    else if (name == "vmf") v = warp::square_to_vmf(s, param);
    else if (name == "uniform_disk") { const Vec2 d = warp::square_to_uniform_disk_concentric(s); v = Vec3(d, 0.f); }
    else if (name == "uniform_triangle") { const Vec2 b = warp::square_to_uniform_triangle(s); v = Vec3(b, 0.f); }
    else throw std::invalid_argument("unknown warp '" + name + "'");
    w(i, 0) = v.x; w(i, 1) = v.y; w(i, 2) = v.z;
  }
  return out;
}

DArray warp_pdf(const std::string& name, const FArray& v, float param) {
  const auto pts = rows3(v, "v");
  DArray out(std::vector<ssize_t>{ssize_t(pts.size())});
  double* o = out.mutable_data();
  for (size_t i = 0; i < pts.size(); ++i) {
    const Vec3& x = pts[i];
    if (name == "uniform_sphere") o[i] = warp::uniform_sphere_pdf();
    else if (name == "uniform_hemisphere") o[i] = warp::uniform_hemisphere_pdf(x);
    else if (name == "cosine_hemisphere") o[i] = warp::cosine_hemisphere_pdf(x);
    else if (name == "uniform_cone") o[i] = warp::uniform_cone_pdf(x, param);
    else if (name == "vmf") o[i] = warp::vmf_pdf_cos(double(x.z), double(param));
    else throw std::invalid_argument("unknown warp '" + name + "'");
  }
  return out;
}

BSDFContext test_context(const Scene& s, int id, const Vec3& wi) {
  if (id < 0 || id >= int(s.bsdfs.nodes.size())) throw std::invalid_argument("BSDF id out of range");
  SurfaceInteraction si;
  si.valid = true;
  si.uv = Vec2(0.5f);
  si.wi = wi;
  return s.bsdfs.resolve(id, si);
}


// --- manifold walk entry points (tests) -----------------------------------------

WalkConfig walk_config(const py::dict& p) {
  WalkConfig c;
  c.threshold = get<double>(p, "threshold", c.threshold);
  c.max_iterations = get<int>(p, "max_iterations", c.max_iterations);
  c.min_step = get<double>(p, "min_step", c.min_step);
  c.step_halvings = get<int>(p, "step_halvings", c.step_halvings);
  if (c.step_halvings < -1 || c.step_halvings > 30) throw std::invalid_argument("step_halvings must be -1 (no limit) or 0..30");
  if (!(c.min_step > 0.0 && c.min_step <= 1.0)) throw std::invalid_argument("min_step must be in (0, 1]");
  c.glossy_threshold = get<float>(p, "glossy_threshold", c.glossy_threshold);
  if (!(c.glossy_threshold >= 0.f)) throw std::invalid_argument("glossy_threshold must be >= 0");
  const std::string form = get<std::string>(p, "form", "direction");
  if (form == "direction") c.form = ConstraintForm::Direction;
  else if (form == "angle") c.form = ConstraintForm::Angle;
  else if (form == "half_vector") c.form = ConstraintForm::HalfVector;
  else throw std::invalid_argument("unknown constraint form '" + form + "'");
  return c;
}

DVec3 dvec3(const py::handle& h) {
  auto a = py::cast<std::vector<double>>(h);
  if (a.size() != 3) throw std::invalid_argument("expected 3 components");
  return DVec3(a[0], a[1], a[2]);
}

py::list chain_points(const ManifoldChain& c) {
  py::list l;
  for (const auto& v : c.v) l.append(std::vector<double>{v.p.x, v.p.y, v.p.z});
  return l;
}

// Trace a seed chain from x_D along `direction` with letters `tau`, optionally
// perturb it, and run the walk toward x_L.
py::dict manifold_walk(const Scene& s, py::object xD, py::object nD, py::object xL, py::object nL,
                       py::object direction, const std::string& tau, const py::dict& cfg) {
  if (!s.committed()) throw std::runtime_error("scene not committed");
  WalkConfig wc = walk_config(cfg);
  wc.record_residuals = true;
  ManifoldWalk walk(s, wc);
  ManifoldChain chain;
  WalkFailure why = WalkFailure::None;
  py::dict r;
  chain.xL = dvec3(xL);
  chain.nL = glm::normalize(dvec3(nL));
  if (!walk.trace_seed(dvec3(xD), glm::normalize(dvec3(nD)), dvec3(direction), tau, chain, why)) {
    r["converged"] = false;
    r["failure"] = std::string(walk_failure_name(why));
    r["stage"] = std::string("seed");
    return r;
  }
  r["seed"] = chain_points(chain);
  const WalkResult res = walk.solve(chain);
  r["converged"] = res.converged;
  r["failure"] = std::string(walk_failure_name(res.failure));
  r["iterations"] = res.iterations;
  r["reprojections"] = res.reprojections;
  r["off_surface"] = res.off_surface;
  r["later_rejections"] = res.later_rejections;
  r["limited_tries"] = std::vector<int>(res.limited_tries.begin(), res.limited_tries.end());
  r["residuals"] = res.residuals;
  r["vertices"] = chain_points(chain);
  if (res.converged) {
    double g = 0.0;
    if (walk.geometry_area(chain, g)) r["G_area"] = g;
    if (walk.geometry_point(chain, g)) r["G_point"] = g;
  }
  // Analytic Jacobian blocks and central finite differences of the constraints
  // (each vertex chart perturbed by +-h), for the derivative test.
  std::vector<double> A, B, D;
  double dL[4], dD[4];
  if (walk.jacobian(chain, A, B, D, dL, dD)) {
    const size_t n = chain.v.size();
    const double h = get<double>(cfg, "fd_step", 1e-6);
    std::vector<double> J(4 * n * n, 0.0), Jfd(4 * n * n, 0.0);
    for (size_t i = 0; i < n; ++i) {
      for (int r2 = 0; r2 < 2; ++r2)
        for (int k = 0; k < 2; ++k) {
          if (i > 0) J[(2 * i + r2) * 2 * n + 2 * (i - 1) + k] = A[4 * i + 2 * r2 + k];
          J[(2 * i + r2) * 2 * n + 2 * i + k] = B[4 * i + 2 * r2 + k];
          if (i + 1 < n) J[(2 * i + r2) * 2 * n + 2 * (i + 1) + k] = D[4 * i + 2 * r2 + k];
        }
    }
    for (size_t j = 0; j < n; ++j) {
      for (int k = 0; k < 2; ++k) {
        std::vector<double> Cp, Cm;
        ManifoldChain cp = chain, cm = chain;
        for (int sgn = -1; sgn <= 1; sgn += 2) {
          ManifoldChain& c = sgn > 0 ? cp : cm;
          const double du = k == 0 ? sgn * h : 0.0, dv = k == 1 ? sgn * h : 0.0;
          const ManifoldVertex m = ManifoldWalk::moved(c.v[j], du, dv);
          c.v[j].p = m.p;
          c.v[j].n = m.n;
        }
        // keep the frame reference tangent fixed: it is a constant of the constraint
        if (!walk.constraints(cp, Cp) || !walk.constraints(cm, Cm)) continue;
        for (size_t row = 0; row < 2 * n; ++row) Jfd[row * 2 * n + 2 * j + k] = (Cp[row] - Cm[row]) / (2 * h);
      }
    }
    r["jacobian"] = J;
    r["jacobian_fd"] = Jfd;
  }
  return r;
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "mpg C++ core";

  py::class_<Scene, std::shared_ptr<Scene>>(m, "Scene")
      .def(py::init<>())
      .def("add_texture_constant", [](Scene& s, py::object v) {
        check_not_committed(s);
        Texture t; t.kind = Texture::Kind::Constant; t.value = vec3(v);
        s.bsdfs.textures.push_back(t);
        return int(s.bsdfs.textures.size()) - 1;
      })
      .def("add_texture_bitmap", [](Scene& s, const FArray& img, py::object to_uv, bool bilinear, const std::string& wrap) {
        check_not_committed(s);
        return add_texture_bitmap(s, img, to_uv, bilinear, wrap);
      }, py::arg("image"), py::arg("to_uv"), py::arg("bilinear") = true, py::arg("wrap") = "repeat")
      .def("add_texture_checker", [](Scene& s, py::object c0, py::object c1, py::object to_uv) {
        check_not_committed(s);
        Texture t; t.kind = Texture::Kind::Checkerboard; t.color0 = vec3(c0); t.color1 = vec3(c1); t.to_uv = mat3(to_uv);
        s.bsdfs.textures.push_back(t);
        return int(s.bsdfs.textures.size()) - 1;
      })
      .def("add_bsdf", [](Scene& s, const std::string& type, const py::dict& p) { check_not_committed(s); return add_bsdf(s, type, p); })
      .def("add_mesh", [](Scene& s, const FArray& pos, const UArray& idx, py::object normals, py::object uvs, int bsdf, bool flip) {
        check_not_committed(s);
        Shape sh;
        sh.kind = Shape::Kind::Mesh;
        sh.positions = rows3(pos, "positions");
        if (idx.ndim() != 2 || idx.shape(1) != 3) throw std::invalid_argument("indices must have shape (M, 3)");
        auto ri = idx.unchecked<2>();
        sh.indices.resize(size_t(idx.shape(0)));
        for (ssize_t i = 0; i < idx.shape(0); ++i) {
          sh.indices[size_t(i)] = glm::uvec3(ri(i, 0), ri(i, 1), ri(i, 2));
          for (int k = 0; k < 3; ++k)
            if (ri(i, k) >= sh.positions.size()) throw std::invalid_argument("triangle index out of range");
        }
        for (const Vec3& p : sh.positions)
          if (!is_finite(p)) throw std::invalid_argument("mesh has non-finite vertex positions");
        if (!normals.is_none()) {
          sh.normals = rows3(py::cast<FArray>(normals), "normals");
          if (sh.normals.size() != sh.positions.size()) throw std::invalid_argument("normals count differs from positions");
        }
        if (!uvs.is_none()) {
          FArray a = py::cast<FArray>(uvs);
          if (a.ndim() != 2 || a.shape(1) != 2 || size_t(a.shape(0)) != sh.positions.size())
            throw std::invalid_argument("uvs must have shape (N, 2)");
          auto r = a.unchecked<2>();
          sh.uvs.resize(size_t(a.shape(0)));
          for (ssize_t i = 0; i < a.shape(0); ++i) sh.uvs[size_t(i)] = Vec2(r(i, 0), r(i, 1));
        }
        if (bsdf < 0 || bsdf >= int(s.bsdfs.nodes.size())) throw std::invalid_argument("BSDF id out of range");
        sh.bsdf = bsdf;
        sh.flip_normals = flip;
        return s.add_shape(std::move(sh));
      }, py::arg("positions"), py::arg("indices"), py::arg("normals") = py::none(), py::arg("uvs") = py::none(),
         py::arg("bsdf"), py::arg("flip_normals") = false)
      .def("add_sphere", [](Scene& s, py::object center, float radius, int bsdf, bool flip) {
        check_not_committed(s);
        if (!(radius > 0.f) || !std::isfinite(radius)) throw std::invalid_argument("sphere radius must be positive");
        if (bsdf < 0 || bsdf >= int(s.bsdfs.nodes.size())) throw std::invalid_argument("BSDF id out of range");
        Shape sh; sh.kind = Shape::Kind::Sphere; sh.center = vec3(center); sh.radius = radius; sh.bsdf = bsdf; sh.flip_normals = flip;
        return s.add_shape(std::move(sh));
      }, py::arg("center"), py::arg("radius"), py::arg("bsdf"), py::arg("flip_normals") = false)
      .def("set_caustic_receiver", [](Scene& s, int shape, bool on) {
        check_not_committed(s);
        if (shape < 0 || shape >= int(s.shapes.size())) throw std::invalid_argument("shape id out of range");
        s.shapes[size_t(shape)].caustic_receiver = on;
      }, py::arg("shape"), py::arg("on") = true)
      .def("add_area_emitter", [](Scene& s, int shape, py::object radiance) {
        check_not_committed(s);
        if (shape < 0 || shape >= int(s.shapes.size())) throw std::invalid_argument("shape id out of range");
        if (!(s.shapes[size_t(shape)].area > 0.f)) throw std::invalid_argument("area emitter on a shape of zero area");
        Emitter e; e.type = Emitter::Type::Area; e.shape = shape; e.value = vec3(radiance);
        return s.add_emitter(e);
      })
      .def("add_point_emitter", [](Scene& s, py::object intensity, py::object position) {
        check_not_committed(s);
        Emitter e; e.type = Emitter::Type::Point; e.value = vec3(intensity); e.position = vec3(position);
        return s.add_emitter(e);
      })
      .def("add_spot_emitter", [](Scene& s, py::object intensity, py::object to_world, float cutoff_deg, float beam_deg) {
        check_not_committed(s);
        Emitter e; e.type = Emitter::Type::Spot; e.value = vec3(intensity);
        const Mat4 m = mat4(to_world);
        e.position = Vec3(m * Vec4(0, 0, 0, 1));
        const Vec3 z = glm::normalize(Vec3(m * Vec4(0, 0, 1, 0)));
        e.frame = Frame::from_normal_tangent(z, Vec3(m * Vec4(1, 0, 0, 0)));
        e.cutoff = glm::radians(cutoff_deg);
        const float beam = glm::radians(std::min(beam_deg, cutoff_deg));
        e.cos_cutoff = std::cos(e.cutoff);
        e.cos_beam = std::cos(beam);
        e.inv_transition = e.cutoff > beam ? 1.f / (e.cutoff - beam) : 0.f;
        return s.add_emitter(e);
      })
      .def("add_directional_emitter", [](Scene& s, py::object irradiance, py::object direction) {
        check_not_committed(s);
        Emitter e; e.type = Emitter::Type::Directional; e.value = vec3(irradiance);
        e.direction = glm::normalize(vec3(direction));
        if (!is_finite(e.direction)) throw std::invalid_argument("directional emitter needs a non-zero direction");
        return s.add_emitter(e);
      })
      .def("add_constant_emitter", [](Scene& s, py::object radiance) {
        check_not_committed(s);
        Emitter e; e.type = Emitter::Type::Constant; e.value = vec3(radiance);
        return s.add_emitter(e);
      })
      .def("add_envmap_emitter", [](Scene& s, const FArray& img, float scale, py::object to_world) {
        check_not_committed(s);
        Emitter e; e.type = Emitter::Type::Envmap; e.scale = scale;
        const int tid = add_texture_bitmap(s, img, DArray(std::vector<ssize_t>{3, 3}, std::vector<double>{1,0,0,0,1,0,0,0,1}.data()), true, "repeat");
        e.env = s.bsdfs.textures[size_t(tid)];
        s.bsdfs.textures.pop_back();
        e.env.wrap = Texture::Wrap::Repeat;
        const Mat4 m = mat4(to_world);
        e.frame = Frame(glm::normalize(Vec3(m[0])), glm::normalize(Vec3(m[1])), glm::normalize(Vec3(m[2])));
        // Importance: a piecewise-constant density on a 2W x 2H grid of the
        // (bilinear) radiance times sin(theta); a floor keeps it positive everywhere.
        if (e.env.width < 2 || e.env.height < 2) throw std::invalid_argument("envmap must be at least 2x2 pixels");
        const int gw = 2 * e.env.width, gh = 2 * e.env.height;
        std::vector<float> w(size_t(gw) * gh);
        double total = 0.0;
        for (int y = 0; y < gh; ++y) {
          const float v = (y + 0.5f) / gh, st = std::sin(kPi * v);
          for (int x = 0; x < gw; ++x) {
            const float l = std::max(0.f, luminance(e.env_lookup(Vec2((x + 0.5f) / gw, v))));
            w[size_t(y) * gw + x] = l * st;
            total += l * st;
          }
        }
        const float floor_w = float(total / double(w.size()) * 1e-3) + 1e-12f;
        for (int y = 0; y < gh; ++y)
          for (int x = 0; x < gw; ++x) w[size_t(y) * gw + x] += floor_w * std::sin(kPi * (y + 0.5f) / gh);
        e.env_dist.build(w, gw, gh);
        return s.add_emitter(std::move(e));
      })
      .def("set_camera", [](Scene& s, py::object to_world, float fov, const std::string& fov_axis, float near_clip,
                            float far_clip, int width, int height, std::vector<int> crop, const std::string& filter,
                            float stddev, float radius) {
        check_not_committed(s);
        Camera& c = s.camera;
        if (width < 1 || height < 1) throw std::invalid_argument("film size must be positive");
        if (!(fov > 0.f && fov < 180.f)) throw std::invalid_argument("fov must be in (0, 180) degrees");
        if (!(near_clip > 0.f && far_clip > near_clip)) throw std::invalid_argument("need 0 < near_clip < far_clip");
        if (crop.size() != 4 || crop[0] < 0 || crop[1] < 0 || crop[2] < 1 || crop[3] < 1 ||
            crop[0] + crop[2] > width || crop[1] + crop[3] > height)
          throw std::invalid_argument("crop window outside the film");
        c.to_world = mat4(to_world);
        c.width = width; c.height = height;
        c.crop_x = crop[0]; c.crop_y = crop[1]; c.crop_w = crop[2]; c.crop_h = crop[3];
        c.near_clip = near_clip; c.far_clip = far_clip;
        const float aspect = float(width) / float(height);
        const float t = std::tan(glm::radians(fov) * 0.5f);
        std::string axis = fov_axis;
        if (axis == "smaller") axis = width <= height ? "x" : "y";
        if (axis == "larger") axis = width > height ? "x" : "y";
        if (axis == "x") { c.tan_half_x = t; c.tan_half_y = t / aspect; }
        else if (axis == "y") { c.tan_half_y = t; c.tan_half_x = t * aspect; }
        else if (axis == "diagonal") {
          const float diag = std::sqrt(aspect * aspect + 1.f);
          c.tan_half_x = t * aspect / diag; c.tan_half_y = t / diag;
        } else throw std::invalid_argument("unknown fov_axis '" + fov_axis + "'");
        FilterSampler::Type ft = filter == "gaussian" ? FilterSampler::Type::Gaussian
                                 : filter == "tent" ? FilterSampler::Type::Tent : FilterSampler::Type::Box;
        if (filter != "gaussian" && filter != "tent" && filter != "box") throw std::invalid_argument("unknown filter '" + filter + "'");
        if (!(stddev > 0.f) || !(radius > 0.f)) throw std::invalid_argument("filter size must be positive");
        c.filter.build(ft, stddev, radius);
      }, py::arg("to_world"), py::arg("fov"), py::arg("fov_axis"), py::arg("near_clip"), py::arg("far_clip"),
         py::arg("width"), py::arg("height"), py::arg("crop"), py::arg("filter") = "box", py::arg("stddev") = 0.5f,
         py::arg("radius") = 1.f)
      .def("commit", [](Scene& s) { py::gil_scoped_release nogil; s.commit(); })
      .def_property_readonly("num_shapes", [](const Scene& s) { return s.shapes.size(); })
      .def_property_readonly("num_emitters", [](const Scene& s) { return s.emitters.size(); })
      .def_property_readonly("num_bsdfs", [](const Scene& s) { return s.bsdfs.nodes.size(); })
      .def_property_readonly("bbox", [](const Scene& s) {
        return std::make_pair(std::vector<float>{s.bbox_min.x, s.bbox_min.y, s.bbox_min.z},
                              std::vector<float>{s.bbox_max.x, s.bbox_max.y, s.bbox_max.z});
      })
      .def("shape_area", [](const Scene& s, int i) { return s.shapes.at(size_t(i)).area; })
      .def("emitter_pmf", [](const Scene& s, int i) { return s.emitter_pmf(i); })
      .def("intersect", [](const Scene& s, py::object o, py::object d) {
        const SurfaceInteraction si = s.intersect(vec3(o), glm::normalize(vec3(d)), 0.f, kInf);
        py::dict r;
        r["valid"] = si.valid;
        if (si.valid) {
          r["t"] = si.t; r["shape"] = si.shape;
          r["p"] = std::vector<float>{si.p.x, si.p.y, si.p.z};
          r["ng"] = std::vector<float>{si.ng.x, si.ng.y, si.ng.z};
          r["ns"] = std::vector<float>{si.sh.n.x, si.sh.n.y, si.sh.n.z};
          r["uv"] = std::vector<float>{si.uv.x, si.uv.y};
        }
        return r;
      });

  py::class_<Integrator, std::shared_ptr<Integrator>>(m, "Integrator")
      .def_property_readonly("chains_active", [](const Integrator& i) {
        auto* p = dynamic_cast<const PathIntegrator*>(&i);
        return p != nullptr && p->chains_active();
      })
      .def_property_readonly("chains_delta_lights", [](const Integrator& i) {
        auto* p = dynamic_cast<const PathIntegrator*>(&i);
        return p != nullptr && p->chains_delta_lights();
      })
      .def_property_readonly("light_trace_glossy_on", [](const Integrator& i) {
        // the light tracer runs in glossy mode (no chain estimator; LightTracer)
        const LightTracer* lt = i.light_tracer();
        return lt != nullptr && lt->glossy();
      })
      .def_property_readonly("glint_emitters", [](const Integrator& i) {
        // the emitters (scene indices) whose glints the walks take ([] when off)
        auto* p = dynamic_cast<const PathIntegrator*>(&i);
        return p && p->glints_on() ? p->glint_lights().emitters : std::vector<int>();
      })
      .def_property_readonly("glint_max_chain", [](const Integrator& i) {
        auto* p = dynamic_cast<const PathIntegrator*>(&i);
        return p && p->glints_on() ? p->glint_lights().mmax : 0;
      })
      .def_property_readonly("light_tracer_on", [](const Integrator& i) {
        // the render passes trace photons (either mode; mpg's photon rate model)
        return i.light_tracer() != nullptr;
      })
      .def_property_readonly("light_trace_off", [](const Integrator& i) {
        // why light_trace > 0 runs no light tracer ("" when it runs or was not asked)
        auto* p = dynamic_cast<const PathIntegrator*>(&i);
        return p ? p->light_trace_off() : std::string();
      })
      .def("trace_photons", [](const Integrator& i, uint64_t count, uint64_t seed, int threads,
                               py::object begin, py::object end) {
        // Photon initialisation of MPG (supplemental Sec. 2): sub-path samples
        // from photons (threads: 0 = all cores; the buffer does not depend on it).
        // begin/end: only photons [begin, end) of the `count`, weighted as in
        // the whole trace (consecutive ranges' buffers, appended, are its buffer).
        if (threads < 0) throw std::invalid_argument("threads must be >= 0");
        // (as signed integers first: a negative bound is a ValueError, not a cast error)
        const long long bs = begin.is_none() ? 0LL : begin.cast<long long>();
        const long long es = end.is_none() ? (long long)count : end.cast<long long>();
        if (bs < 0 || es < bs || (unsigned long long)es > count)
          throw std::invalid_argument("trace_photons: need 0 <= begin <= end <= count, got begin " +
                                      std::to_string(bs) + ", end " + std::to_string(es) + ", count " +
                                      std::to_string(count));
        const uint64_t b = uint64_t(bs), e = uint64_t(es);
        auto buf = std::make_shared<SubpathBuffer>();
        auto* p = dynamic_cast<const PathIntegrator*>(&i);
        if (p && p->chains() && e > b) {
          py::gil_scoped_release nogil;
          p->chains()->trace_photons(count, seed, buf->v, threads, b, e);
        }
        return buf;
      }, py::arg("count"), py::arg("seed") = 0, py::arg("threads") = 0, py::arg("begin") = py::none(),
         py::arg("end") = py::none());
  m.def("mis_pair", [](const Integrator& i, py::object o, py::object d, py::object omega_D, py::object seed_dir,
                       const std::string& tau) -> py::object {
    // The MIS densities (a, b) of one chain path on the estimator's and on the
    // path tracer's side (tests; ChainEstimator::mis_pair).
    auto* p = dynamic_cast<const PathIntegrator*>(&i);
    if (!p || !p->chains()) throw std::invalid_argument("the integrator has no chain estimator");
    double ab[4] = {0.0, 0.0, 0.0, 0.0};
    if (!p->chains()->mis_pair(vec3(o), vec3(d), vec3(omega_D), vec3(seed_dir), tau, ab)) return py::none();
    return py::make_tuple(ab[0], ab[1], ab[2], ab[3]);
  });
  m.def("make_integrator", &make_integrator, py::arg("scene"), py::arg("type"), py::arg("params"));

  py::class_<RenderJob, std::shared_ptr<RenderJob>>(m, "RenderJob")
      .def(py::init([](std::shared_ptr<Scene> scene, std::shared_ptr<Integrator> integ, int spp, uint64_t seed,
                       uint64_t pass, int threads, py::object chain_rate_map, bool record_costs,
                       py::object delta_split_map, py::object pixel_split_map, bool stratify,
                       uint64_t sample_offset, py::object guided_trace_map, bool record_classes,
                       bool light_trace, py::object delta_branch_map, bool record_branch,
                       int lt_wave_blocks, uint64_t sequence_epoch, py::object deep_rate_map,
                       bool record_delta) {
        if (!scene->committed()) throw std::runtime_error("scene not committed");
        if (spp < 1) throw std::invalid_argument("spp must be >= 1");
        PassConfig cfg; cfg.spp = spp; cfg.seed = seed; cfg.pass = pass; cfg.threads = threads;
        cfg.record_costs = record_costs;
        cfg.record_classes = record_classes;
        cfg.record_delta = record_delta;
        cfg.record_branch = record_branch;
        cfg.light_trace = light_trace;
        cfg.lt_wave_blocks = lt_wave_blocks;
        cfg.stratify = stratify;
        cfg.sample_offset = sample_offset;
        cfg.sequence_epoch = sequence_epoch;
        if (!chain_rate_map.is_none()) {
          auto m = pixel_map(chain_rate_map, scene->camera, "chain_rate_map");
          bool zero = false;
          for (float q : *m) {
            if (!(q == 0.f || (q >= 1e-3f && q <= 1.f)))
              throw std::invalid_argument("chain_rate_map values must be 0 or in [0.001, 1]");
            zero = zero || q == 0.f;
          }
          auto* pi = dynamic_cast<const PathIntegrator*>(integ.get());
          if (zero && pi && pi->chains_delta_lights())
            throw std::invalid_argument(
                "chain_rate_map values of 0 hand a pixel's chain light to the path tracer, which cannot "
                "reach a point or spot light through specular chains; this scene has one");
          cfg.chain_rate_map = std::move(m);
        }
        if (!delta_split_map.is_none()) {
          auto m = count_map(delta_split_map, scene->camera, "delta_split_map");
          auto* pi = dynamic_cast<const PathIntegrator*>(integ.get());
          if (pi && pi->camera_delta() != PathParams::CameraDelta::All)
            throw std::invalid_argument("delta_split_map needs the integrator's camera_delta = all");
          cfg.delta_split_map = std::move(m);
        }
        if (!delta_branch_map.is_none()) {
          auto m = pixel_map(delta_branch_map, scene->camera, "delta_branch_map");
          for (float v : *m)
            if (!(v == 0.f || v == 1.f)) throw std::invalid_argument("delta_branch_map values must be 0 or 1");
          cfg.delta_branch_map = std::move(m);
        }
        if (!pixel_split_map.is_none()) {
          auto m = count_map(pixel_split_map, scene->camera, "pixel_split_map");
          if (record_costs)   // the per-sample records would see the last camera sample only
            throw std::invalid_argument("pixel_split_map cannot be used with record_costs");
          cfg.pixel_split_map = std::move(m);
        }
        if (!guided_trace_map.is_none()) {
          auto m = pixel_map(guided_trace_map, scene->camera, "guided_trace_map");
          for (float v : *m)
            if (!(v >= 0.f && v <= 64.f && v == std::floor(v)))
              throw std::invalid_argument("guided_trace_map values must be integers in 0..64");
          cfg.guided_trace_map = std::move(m);
        }
        if (!deep_rate_map.is_none()) {
          auto m = pixel_map(deep_rate_map, scene->camera, "deep_rate_map");
          for (float q : *m)
            if (!(q == 0.f || (q >= 1e-3f && q <= 1.f)))
              throw std::invalid_argument("deep_rate_map values must be 0 or in [0.001, 1]");
          cfg.deep_rate_map = std::move(m);
        }
        auto job = std::make_shared<RenderJob>(scene, integ, cfg);
        job->start();
        return job;
      }), py::arg("scene"), py::arg("integrator"), py::arg("spp"), py::arg("seed") = 0, py::arg("pass_index") = 0,
         py::arg("threads") = 0, py::arg("chain_rate_map") = py::none(), py::arg("record_costs") = false,
         py::arg("delta_split_map") = py::none(), py::arg("pixel_split_map") = py::none(),
         py::arg("stratify") = false, py::arg("sample_offset") = 0, py::arg("guided_trace_map") = py::none(),
         py::arg("record_classes") = false, py::arg("light_trace") = true, py::arg("delta_branch_map") = py::none(),
         py::arg("record_branch") = false, py::arg("lt_wave_blocks") = 1024,
         py::arg("sequence_epoch") = 0, py::arg("deep_rate_map") = py::none(),
         py::arg("record_delta") = false)
      .def("wait", [](RenderJob& j, double seconds) { py::gil_scoped_release nogil; return j.wait_for(seconds); })
      .def("cancel", &RenderJob::cancel)
      .def_property_readonly("progress", &RenderJob::progress)
      .def("result", [](py::object self) {
        RenderJob& j = self.cast<RenderJob&>();
        // (the arrays are views of the job's buffers: not while its threads write them)
        if (!j.wait_for(0.0)) throw std::runtime_error("RenderJob.result(): the pass is still running; wait() first");
        return pass_to_dict(j.result(), self);
      });


  py::class_<SubpathBuffer, std::shared_ptr<SubpathBuffer>>(m, "SubpathBuffer")
      .def("__len__", [](const SubpathBuffer& b) { return b.v.size(); })
      .def_property_readonly("nbytes", [](const SubpathBuffer& b) { return b.v.size() * sizeof(SubpathSample); })
      .def("scaled", [](const SubpathBuffer& b, float f) {
        // A copy with every weight times f (mpg.guiding: the photon guide's
        // samples put on the training samples' scale)
        auto out = std::make_shared<SubpathBuffer>();
        out->v = b.v;
        for (auto& s : out->v) s.weight *= f;
        return out;
      })
      .def("arrays", [](const SubpathBuffer& b) {
        // The samples as numpy arrays (tests, inspection): xD, xL, dir (decoded), n, tau, weight.
        const ssize_t k = ssize_t(b.v.size());
        FArray xd(std::vector<ssize_t>{k, 3}), xl(std::vector<ssize_t>{k, 3}), dir(std::vector<ssize_t>{k, 3});
        py::array_t<int> n(k);
        py::array_t<uint16_t> tau(k);
        FArray w(k);
        for (ssize_t j = 0; j < k; ++j) {
          const SubpathSample& s = b.v[size_t(j)];
          const Vec3 d = oct_decode(Vec2(s.dir[0], s.dir[1]));
          for (int a = 0; a < 3; ++a) {
            xd.mutable_at(j, a) = s.xD[a]; xl.mutable_at(j, a) = s.xL[a]; dir.mutable_at(j, a) = d[a];
          }
          n.mutable_at(j) = s.n;
          tau.mutable_at(j) = s.tau;
          w.mutable_at(j) = s.weight;
        }
        py::dict r;
        r["xD"] = xd; r["xL"] = xl; r["dir"] = dir; r["n"] = n; r["tau"] = tau; r["weight"] = w;
        return r;
      });

  m.def("check_guide_config", [](float c, float epsilon, const std::string& filter, int threshold,
                                  const std::string& structure, int knn_k, float anchor) {
    validate(guide_config(c, epsilon, 36, 1, filter, threshold, structure, knn_k, anchor));
  }, py::arg("c") = 1.f, py::arg("epsilon") = 0.1f, py::arg("filter") = "nearest", py::arg("threshold") = 0,
     py::arg("structure") = "stree", py::arg("knn_k") = 0, py::arg("anchor") = 0.f,
     "Raise ValueError naming the parameter when GuidingState.build would reject these options.");

  py::class_<GuidingState, std::shared_ptr<GuidingState>>(m, "GuidingState")
      .def(py::init<>())
      .def("build_from", [](GuidingState& g, const std::vector<std::shared_ptr<SubpathBuffer>>& bufs,
                            py::object bmin, py::object bmax, float c, float epsilon, int max_depth, int threads,
                            const std::string& filter, int threshold, const std::string& structure, int knn_k, float anchor) {
        std::vector<SubpathSample> all;
        size_t total = 0;
        for (const auto& b : bufs) total += b->v.size();
        all.reserve(total);
        for (const auto& b : bufs) all.insert(all.end(), b->v.begin(), b->v.end());
        const GuideConfig cfg = guide_config(c, epsilon, max_depth, threads, filter, threshold, structure, knn_k, anchor);
        const Vec3 lo = vec3(bmin), hi = vec3(bmax);
        py::gil_scoped_release nogil;
        g.build(all, lo, hi, cfg);
        return all.size();
      }, py::arg("buffers"), py::arg("bmin"), py::arg("bmax"), py::arg("c") = 1.f, py::arg("epsilon") = 0.1f,
         py::arg("max_depth") = 36, py::arg("threads") = 2, py::arg("filter") = "nearest", py::arg("threshold") = 0,
         py::arg("structure") = "stree", py::arg("knn_k") = 0, py::arg("anchor") = 0.f,
         "Build from training buffers. filter: nearest | stochastic | none (stree_filter); threshold: a fixed "
         "split threshold, 0 = c sqrt(|S|) (stree_threshold); structure: stree | knn (guide_structure); "
         "knn_k: neighbours per kNN query, 0 = ceil(c sqrt(|S|)); anchor: lobes anchored at x_D + omega_D * "
         "anchor * |x_L - x_D| and aimed from the query's x_D, 0 = centred on omega_D (lobe_anchor).")
      .def("build", [](GuidingState& g, const FArray& xD, const FArray& xL, const FArray& dirs,
                       py::array_t<int, py::array::c_style | py::array::forcecast> n,
                       py::array_t<uint16_t, py::array::c_style | py::array::forcecast> tau, const FArray& weight,
                       py::object bmin, py::object bmax, float c, float epsilon, int max_depth, int threads,
                       const std::string& filter, int threshold, const std::string& structure, int knn_k, float anchor) {
        const auto pd = rows3(xD, "xD"), pl = rows3(xL, "xL"), dd = rows3(dirs, "dirs");
        const size_t N = pd.size();
        if (pl.size() != N || dd.size() != N || size_t(n.size()) != N || size_t(tau.size()) != N ||
            size_t(weight.size()) != N)
          throw std::invalid_argument("all sample arrays must have the same length");
        std::vector<SubpathSample> s(N);
        for (size_t i = 0; i < N; ++i) {
          SubpathSample& x = s[i];
          for (int k = 0; k < 3; ++k) { x.xD[k] = pd[i][k]; x.xL[k] = pl[i][k]; }
          const Vec2 e = oct_encode(glm::normalize(dd[i]));
          x.dir[0] = e.x; x.dir[1] = e.y;
          x.n = uint8_t(n.data()[i]);
          x.tau = tau.data()[i];
          x.weight = weight.data()[i];
          x.flags = 0;
        }
        const GuideConfig cfg = guide_config(c, epsilon, max_depth, threads, filter, threshold, structure, knn_k, anchor);
        const Vec3 lo = vec3(bmin), hi = vec3(bmax);  // with the GIL held
        py::gil_scoped_release nogil;
        g.build(s, lo, hi, cfg);
      }, py::arg("xD"), py::arg("xL"), py::arg("dirs"), py::arg("n"), py::arg("tau"), py::arg("weight"),
         py::arg("bmin"), py::arg("bmax"), py::arg("c") = 1.f, py::arg("epsilon") = 0.1f,
         py::arg("max_depth") = 36, py::arg("threads") = 2, py::arg("filter") = "nearest", py::arg("threshold") = 0,
         py::arg("structure") = "stree", py::arg("knn_k") = 0, py::arg("anchor") = 0.f)
      .def_property_readonly("num_leaves", [](const GuidingState& g) { return g.tree().num_leaves(); })
      .def_property_readonly("num_nodes", [](const GuidingState& g) { return g.tree().num_nodes(); })
      .def_property_readonly("samples_stored", [](const GuidingState& g) { return g.num_samples_stored(); })
      .def_property_readonly("memory_bytes", &GuidingState::memory_bytes)
      .def_property_readonly("samples_input", &GuidingState::num_samples_input)
      .def_property_readonly("structure", [](const GuidingState& g) { return guide_structure_name(g.config().structure); })
      .def_property_readonly("filter", [](const GuidingState& g) { return stree_filter_name(g.config().stree.filter); })
      .def_property_readonly("knn_k", [](const GuidingState& g) { return g.knn_k(); })
      .def_property_readonly("valid", &GuidingState::valid)
      .def("query_pmf_n", [](const GuidingState& g, py::object xD, py::object xL) -> py::object {
        // P_e(n), n = 1..16, of the distribution the renderer gets for (x_D, x_L); None without one
        const Vec3 a = vec3(xD), b = vec3(xL);
        const ChainDistribution* d = g.query(a, b);
        if (!d) return py::none();
        std::vector<float> p(ChainDistribution::kMaxN);
        for (int n = 1; n <= ChainDistribution::kMaxN; ++n) p[size_t(n - 1)] = d->pmf_n(n);
        return py::cast(p);
      })
      .def("time_queries", [](const GuidingState& g, const FArray& xD, const FArray& xL) {
        // Seconds for query() of every (x_D, x_L) row on this thread (benchmarks):
        // the leaf lookup for stree, the k-NN search and distribution build for knn.
        const auto pd = rows3(xD, "xD"), pl = rows3(xL, "xL");
        if (pd.size() != pl.size()) throw std::invalid_argument("xD and xL must have the same length");
        py::gil_scoped_release nogil;
        const auto t0 = std::chrono::steady_clock::now();
        size_t found = 0;
        for (size_t i = 0; i < pd.size(); ++i) found += g.query(pd[i], pl[i]) != nullptr;
        const double sec = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        return std::make_pair(sec, found);
      })
      .def("knn_neighbours", [](const GuidingState& g, py::object xD, py::object xL) {
        if (g.config().structure != GuideStructure::Knn) throw std::invalid_argument("not a knn guiding state");
        std::vector<uint32_t> out;
        g.knn_neighbours(vec3(xD), vec3(xL), out);
        return out;
      })
      .def_property_readonly("threshold", [](const GuidingState& g) { return g.tree().threshold(); })
      .def_property_readonly("build_seconds", &GuidingState::build_seconds)
      .def_property_readonly("structure_seconds", &GuidingState::structure_seconds)
      .def("leaf_of", [](const GuidingState& g, py::object xD, py::object xL) { return g.tree().leaf_of(vec3(xD), vec3(xL)); })
      .def("leaf_of_descent", [](const GuidingState& g, py::object xD, py::object xL) {
        float q[6];
        g.tree().normalise(vec3(xD), vec3(xL), q);
        return g.tree().leaf_of_descent(q);
      })
      .def("leaf", [](const GuidingState& g, int i) {
        if (i < 0 || size_t(i) >= g.tree().num_leaves()) throw std::out_of_range("leaf index");
        const STree::Leaf& l = g.tree().leaf(i);
        const ssize_t k = ssize_t(l.size());
        FArray xd(std::vector<ssize_t>{k, 3}), xl(std::vector<ssize_t>{k, 3});
        py::array_t<bool> filt(std::vector<ssize_t>{k});
        ssize_t j = 0;
        auto put = [&](const SubpathSample& s, bool f) {
          for (int a = 0; a < 3; ++a) { xd.mutable_at(j, a) = s.xD[a]; xl.mutable_at(j, a) = s.xL[a]; }
          filt.mutable_at(j) = f;
          ++j;
        };
        for (const SubpathSample& s : g.tree().unfiltered(i)) put(s, false);
        for (uint32_t c : g.tree().filtered(i)) put(g.tree().samples()[c], true);
        py::dict r;
        r["xD"] = xd; r["xL"] = xl; r["filtered"] = filt; r["unfiltered"] = l.unfiltered; r["depth"] = l.depth;
        r["lo"] = std::vector<float>(l.lo, l.lo + 6); r["hi"] = std::vector<float>(l.hi, l.hi + 6);
        return r;
      })
      .def("normalise", [](const GuidingState& g, py::object xD, py::object xL) {
        float q[6]; g.normalise(vec3(xD), vec3(xL), q); return std::vector<float>(q, q + 6); })
      .def("pmf_n", [](const GuidingState& g, int leaf, int n) { return g.distribution(leaf).pmf_n(n); })
      .def("leaf_anchor", [](const GuidingState& g, int leaf) { return g.distribution(leaf).anchor(); },
           "The anchor leaf's lobes use (0: centred on their directions; lobe_anchor)")
      .def("leaf_active", [](const GuidingState& g, int leaf) {
        return g.tree().leaf(leaf).unfiltered > 0 && !g.distribution(leaf).empty(); },
           "Does a query reach this leaf's distribution (unfiltered samples: selective activation)?")
      .def("pmf_tau", [](const GuidingState& g, int leaf, int n, uint16_t tau) { return g.distribution(leaf).pmf_tau(n, tau); })
      .def("sample_dir", [](const GuidingState& g, int leaf, int n, uint16_t tau, const FArray& u, py::object xD,
                            float kappa_cap) {
        if (u.ndim() != 2 || u.shape(1) != 3) throw std::invalid_argument("u must have shape (N, 3)");
        if (!(kappa_cap >= 1e-3f)) throw std::invalid_argument("kappa_cap must be >= 0.001");
        const ChainDistribution& d = g.distribution(leaf);
        if (d.anchored() && xD.is_none())
          throw std::invalid_argument("the leaf's lobes are anchored (lobe_anchor): pass xD, the point they aim from");
        const Vec3 p = xD.is_none() ? Vec3(0.f) : vec3(xD);
        FArray out(std::vector<ssize_t>{u.shape(0), 3});
        for (ssize_t i = 0; i < u.shape(0); ++i) {
          Vec3 w(0.f);
          if (!d.sample_dir(n, tau, u.at(i, 0), Vec2(u.at(i, 1), u.at(i, 2)), p, w, kappa_cap)) w = Vec3(0.f);
          out.mutable_at(i, 0) = w.x; out.mutable_at(i, 1) = w.y; out.mutable_at(i, 2) = w.z;
        }
        return out;
      }, py::arg("leaf"), py::arg("n"), py::arg("tau"), py::arg("u"), py::arg("xD") = py::none(),
         py::arg("kappa_cap") = std::numeric_limits<float>::infinity(),
         "Directions from leaf's lobes of (n, tau) for u (N x 3: lobe, then the vMF pair), seen from xD "
         "(anchored lobes aim from it and need it; others ignore it); kappa_cap caps each lobe's kappa "
         "(the guided trace's defensive lobes).")
      .def("pdf_dir", [](const GuidingState& g, int leaf, int n, uint16_t tau, const FArray& dirs, py::object xD,
                         double defensive, float kappa_cap) {
        const auto d = rows3(dirs, "dirs");
        if (!(defensive >= 0.0 && defensive <= 1.0)) throw std::invalid_argument("defensive must be in [0, 1]");
        if (!(kappa_cap >= 1e-3f)) throw std::invalid_argument("kappa_cap must be >= 0.001");
        if (g.distribution(leaf).anchored() && xD.is_none())
          throw std::invalid_argument("the leaf's lobes are anchored (lobe_anchor): pass xD, the point they aim from");
        const Vec3 p = xD.is_none() ? Vec3(0.f) : vec3(xD);
        DArray out(std::vector<ssize_t>{ssize_t(d.size())});
        const ChainDistribution& cd = g.distribution(leaf);
        for (size_t i = 0; i < d.size(); ++i)
          out.mutable_data()[i] = defensive > 0.0 ? cd.pdf_dir_defensive(n, tau, p, d[i], defensive, kappa_cap)
                                                  : double(cd.pdf_dir(n, tau, p, d[i]));
        return out;
      }, py::arg("leaf"), py::arg("n"), py::arg("tau"), py::arg("dirs"), py::arg("xD") = py::none(),
         py::arg("defensive") = 0.0, py::arg("kappa_cap") = std::numeric_limits<float>::infinity(),
         "The density of sample_dir's directions; with defensive > 0, (1 - defensive) of it plus defensive "
         "times the density of the lobes with kappa capped at kappa_cap (the guided trace's mixture).");
  m.attr("SUBPATH_SAMPLE_BYTES") = sizeof(SubpathSample);
  m.def("warp_sample", &warp_sample, py::arg("name"), py::arg("u"), py::arg("param") = 0.f);
  // DiscreteDistribution::sample on weights for each u: (index, rescaled u) (tests).
  m.def("discrete_sample", [](const FArray& weights, const FArray& u) {
    if (weights.ndim() != 1 || u.ndim() != 1) throw std::invalid_argument("weights and u must be 1-D");
    const std::vector<float> w(weights.data(), weights.data() + weights.shape(0));
    const DiscreteDistribution d(w);
    if (d.empty()) throw std::invalid_argument("weights must have a positive finite sum");
    const ssize_t n = u.shape(0);
    py::array_t<int64_t> idx(n);
    FArray out(n);
    for (ssize_t i = 0; i < n; ++i) {
      float x = u.data()[i];
      if (!(x >= 0.f && x < 1.f)) throw std::invalid_argument("u must lie in [0, 1)");
      idx.mutable_data()[i] = int64_t(d.sample(x));
      out.mutable_data()[i] = x;
    }
    return py::make_tuple(idx, out);
  }, py::arg("weights"), py::arg("u"));
  m.def("warp_pdf", &warp_pdf, py::arg("name"), py::arg("v"), py::arg("param") = 0.f);
  // Points start .. start + n - 1 of the shifted Sobol (0,2)-sequence the
  // stratified sampler gives a pixel's positions (tests): an (n, 2) array.
  m.def("sobol_2d", [](int64_t n, uint64_t start, uint32_t shift0, uint32_t shift1) {
    if (n < 0 || n > (int64_t(1) << 26)) throw std::invalid_argument("n must be in [0, 2^26]");
    if (start + uint64_t(n) > (uint64_t(1) << 32)) throw std::invalid_argument("indices must stay below 2^32");
    FArray out(std::vector<ssize_t>{ssize_t(n), 2});
    for (int64_t i = 0; i < n; ++i) {
      float u0, u1;
      shifted_sobol_2d(uint32_t(start + uint64_t(i)), shift0, shift1, u0, u1);
      out.mutable_at(i, 0) = u0;
      out.mutable_at(i, 1) = u1;
    }
    return out;
  }, py::arg("n"), py::arg("start") = 0, py::arg("shift0") = 0, py::arg("shift1") = 0);
  m.def("bsdf_sample", [](const Scene& s, int id, py::object wi_o, const FArray& u) {
    const Vec3 wi = glm::normalize(vec3(wi_o));
    if (u.ndim() != 2 || u.shape(1) != 3) throw std::invalid_argument("u must have shape (N, 3)");
    const ssize_t n = u.shape(0);
    const BSDFContext c = test_context(s, id, wi);
    FArray wo(std::vector<ssize_t>{n, 3}), weight(std::vector<ssize_t>{n, 3});
    FArray pdf(std::vector<ssize_t>{n});
    py::array_t<bool> delta(std::vector<ssize_t>{n});
    auto r = u.unchecked<3 - 1>();
    auto W = wo.mutable_unchecked<2>(); auto G = weight.mutable_unchecked<2>();
    auto P = pdf.mutable_unchecked<1>(); auto D = delta.mutable_unchecked<1>();
    for (ssize_t i = 0; i < n; ++i) {
      Vec3 w(0.f);
      const BSDFSample bs = s.bsdfs.sample(c, wi, r(i, 0), Vec2(r(i, 1), r(i, 2)), w);
      W(i, 0) = w.x; W(i, 1) = w.y; W(i, 2) = w.z;
      G(i, 0) = bs.weight.x; G(i, 1) = bs.weight.y; G(i, 2) = bs.weight.z;
      P(i) = bs.pdf; D(i) = bs.delta;
    }
    return py::make_tuple(wo, weight, pdf, delta);
  });
  m.def("bsdf_eval", [](const Scene& s, int id, py::object wi_o, const FArray& wo) {
    const Vec3 wi = glm::normalize(vec3(wi_o));
    const auto dirs = rows3(wo, "wo");
    const BSDFContext c = test_context(s, id, wi);
    FArray out(std::vector<ssize_t>{ssize_t(dirs.size()), 3});
    auto o = out.mutable_unchecked<2>();
    for (size_t i = 0; i < dirs.size(); ++i) {
      const Color f = s.bsdfs.eval(c, wi, dirs[i]);
      o(ssize_t(i), 0) = f.x; o(ssize_t(i), 1) = f.y; o(ssize_t(i), 2) = f.z;
    }
    return out;
  });
  m.def("bsdf_pdf", [](const Scene& s, int id, py::object wi_o, const FArray& wo) {
    const Vec3 wi = glm::normalize(vec3(wi_o));
    const auto dirs = rows3(wo, "wo");
    const BSDFContext c = test_context(s, id, wi);
    DArray out(std::vector<ssize_t>{ssize_t(dirs.size())});
    for (size_t i = 0; i < dirs.size(); ++i) out.mutable_data()[i] = s.bsdfs.pdf(c, wi, dirs[i]);
    return out;
  });
  m.def("fresnel_dielectric", [](float cos_i, float eta) {
    const DielectricFresnel f = fresnel_dielectric(cos_i, eta);
    return py::make_tuple(f.F, f.cos_t, f.eta_it, f.eta_ti);
  });
  m.def("fresnel_conductor", [](float cos_i, float eta, float k) { return fresnel_conductor_1(cos_i, eta, k); });
  m.def("fresnel_diffuse_reflectance", &fresnel_diffuse_reflectance);
  m.def("bernoulli_counts", [](double p, int n, int max_trials, uint64_t seed, double beta) {
    // n counts K' of rounds that, with probability beta, run a synthetic trial
    // succeeding with probability p and otherwise succeed at once (beta = 1:
    // SMS's estimate of 1/p; ChainEstimator::mis_rounds in general).
    PCG32 rng = make_stream(seed, 0, 0, 0);
    py::array_t<double> out(std::vector<ssize_t>{n});
    int capped_total = 0;
    for (int i = 0; i < n; ++i) {
      bool capped = false;
      out.mutable_data()[i] = bernoulli_count(
          [&] { return mis_round(beta, [&] { return rng.next_double(); }, [&] { return rng.next_double() < p; }); },
          max_trials, capped);
      capped_total += capped;
    }
    return py::make_tuple(out, capped_total);
  }, py::arg("p"), py::arg("n"), py::arg("max_trials"), py::arg("seed") = 0, py::arg("beta") = 1.0);
  m.def("manifold_walk", &manifold_walk, py::arg("scene"), py::arg("xD"), py::arg("nD"), py::arg("xL"),
        py::arg("nL"), py::arg("direction"), py::arg("tau"), py::arg("config") = py::dict());
}
