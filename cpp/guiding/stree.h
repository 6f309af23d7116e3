// The 6D spatial tree over (x_D, x_L) of MPG (Sec. 5.6, supplemental Sec. 3.3):
// a binary tree splitting at the midpoint and cycling the six axes while a
// node holds more than c sqrt(|S|) unfiltered samples (or a fixed threshold,
// supplemental Fig. 2), with one of three spatial filters (paper Fig. 14,
// supplemental Fig. 1):
//  - nearest (the paper's): on every split, the floor(eps k) unfiltered
//    samples of each side nearest the plane (k = the node's unfiltered count)
//    are copied to the other child, marked filtered; copies are never copied
//    again, do not count toward the split threshold, and are dropped when
//    farther than 2 eps x the child's extent from the child's box;
//  - stochastic (Mueller 2019): no copies; once the tree is built, each
//    sample is jittered once by a uniform offset of +-eps x its leaf's extent
//    on every axis and moved to the leaf of the jittered position;
//  - none: no copies, no jitter.
// Rebuilt from scratch from one iteration's samples.
//
// Build: the midpoint splits cycling the axes are the bits of a 6D Morton
// code, so the samples are sorted once by (code, content hash) - a canonical
// order - and every node's unfiltered samples are then a contiguous range of
// that array (no partitioning). Filtered copies are indices into it. The
// tree and the leaf contents therefore depend neither on the input order nor
// on the number of threads.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "guiding/subpath_sample.h"

namespace mpg {

enum class STreeFilter { Nearest, Stochastic, None };
STreeFilter parse_stree_filter(const std::string& s);  // throws std::invalid_argument
const char* stree_filter_name(STreeFilter f);

struct STreeConfig {
  float c = 1.f;           // split while a node holds more than c sqrt(|S|) unfiltered samples
  float epsilon = 0.1f;    // filter width; 0 disables filtering
  STreeFilter filter = STreeFilter::Nearest;
  int threshold = 0;       // a fixed split threshold; 0: c sqrt(|S|) (MPG Sec. 5.6, footnote 8)
  int max_depth = 36;      // depth cap (6 levels per halving of every axis; at most 60)
  int threads = 2;         // build threads (the result does not depend on it)
};

// The cube around the scene bounds that maps (x_D, x_L) to [0,1]^6.
struct Cube6 {
  Vec3 origin{0.f};
  float scale = 1.f;  // 1 / cube side
  void fit(const Vec3& bmin, const Vec3& bmax);
  void normalise(const Vec3& xD, const Vec3& xL, float out[6]) const {
    const Vec3 a = (xD - origin) * scale, b = (xL - origin) * scale;
    out[0] = a.x; out[1] = a.y; out[2] = a.z;
    out[3] = b.x; out[4] = b.y; out[5] = b.z;
  }
  float coord(const SubpathSample& s, int axis) const {
    return axis < 3 ? (s.xD[axis] - origin[axis]) * scale : (s.xL[axis - 3] - origin[axis - 3]) * scale;
  }
};

class STree {
 public:
  struct Node {
    int child[2] = {-1, -1};
    int leaf = -1;          // index into leaves_ for leaf nodes
    uint8_t axis = 0;
    float split = 0.5f;
  };
  struct Leaf {
    uint32_t begin = 0;     // its unfiltered samples: samples_[begin, begin + unfiltered)
    int unfiltered = 0;
    std::vector<uint32_t> filtered;  // filtered copies (nearest filter): indices into samples_
    int depth = 0;
    float lo[6], hi[6];     // box in normalised coordinates
    size_t size() const { return size_t(unfiltered) + filtered.size(); }
  };

  void build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
             const STreeConfig& cfg);
  bool empty() const { return nodes_.empty(); }
  // Leaf index of a configuration (always a leaf; -1 if the tree is empty).
  int leaf_of(const Vec3& xD, const Vec3& xL) const;
  int leaf_of_normalised(const float q[6]) const;
  // The same leaf by the plain descent from the root (tests compare the two).
  int leaf_of_descent(const float q[6]) const { return descend(0, q); }
  const Leaf& leaf(int i) const { return leaves_[size_t(i)]; }
  SampleSpan unfiltered(int i) const {
    const Leaf& l = leaves_[size_t(i)];
    return {samples_.data() + l.begin, size_t(l.unfiltered)};
  }
  const std::vector<uint32_t>& filtered(int i) const { return leaves_[size_t(i)].filtered; }
  // All samples, each once (unfiltered), grouped by leaf.
  const std::vector<SubpathSample>& samples() const { return samples_; }
  size_t num_leaves() const { return leaves_.size(); }
  size_t num_nodes() const { return nodes_.size(); }
  size_t num_samples_stored() const;
  // Bytes the built tree keeps: nodes, the top table, leaves with their
  // filtered copies' indices, and the samples (and the build's scratch, which
  // the build frees: 0 after it).
  size_t memory_bytes() const;
  // Normalised 6D coordinates in [0,1]^6 (the cube around the scene bounds).
  void normalise(const Vec3& xD, const Vec3& xL, float out[6]) const { cube_.normalise(xD, xL, out); }
  const Cube6& cube() const { return cube_; }
  float threshold() const { return threshold_; }

 private:
  struct BuildNode;
  struct TaskQueue;
  void sort_samples(const std::vector<SubpathSample>& in);
  void build_rec(BuildNode& node, uint32_t b, uint32_t e, std::vector<uint32_t> filt, int depth,
                 const float lo[6], const float hi[6], TaskQueue& tq);
  void stochastic_regroup();
  int flatten(BuildNode& b);
  int descend(int node, const float q[6]) const;
  void build_top();

  std::vector<Node> nodes_;
  // Where the descent of a point stands after the splits at the grid lines
  // 1/4, 1/2, 3/4 of every axis: the node for each of the 4^6 cells of that
  // grid (a leaf, or the first node splitting elsewhere). A query reads it
  // and descends from there: the first ~12 levels' dependent loads become one.
  std::vector<int> top_;
  std::vector<Leaf> leaves_;
  std::vector<SubpathSample> samples_;  // every input sample once, grouped by leaf
  // during the build only: Morton codes and per-axis coordinates of samples_
  std::vector<uint64_t> codes_;
  std::vector<float> coords_[6];
  int code_bits_ = 0;  // bits per axis in codes_
  Cube6 cube_;
  float threshold_ = 1.f;
  STreeConfig cfg_;
};

}  // namespace mpg
