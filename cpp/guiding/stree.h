// The 6D spatial tree over (x_D, x_L) of MPG (Sec. 5.5, supplemental Sec. 3.3):
// a binary tree splitting at the midpoint and cycling the six axes while a
// node holds more than c sqrt(|S|) samples, with epsilon-overlap filtering on
// every split (the floor(eps k) samples nearest the plane are copied to the
// other child, marked filtered; samples farther than 2 eps x the extent from
// a child's box are dropped). Rebuilt from scratch from one iteration's samples.
#pragma once

#include <memory>
#include <vector>

#include "guiding/subpath_sample.h"

namespace mpg {

struct STreeConfig {
  float c = 1.f;           // split while a node holds more than c sqrt(|S|) samples
  float epsilon = 0.1f;    // overlap filtering; 0 disables it
  int max_depth = 36;      // depth cap (6 levels per halving of every axis)
  int parallel_depth = 2;  // subtrees below this depth are built on their own threads
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
    std::vector<SubpathSample> samples;
    int unfiltered = 0;     // samples that are not filtered copies
    int depth = 0;
    float lo[6], hi[6];     // box in normalised coordinates
  };

  void build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
             const STreeConfig& cfg);
  bool empty() const { return nodes_.empty(); }
  // Leaf index of a configuration (always a leaf; -1 if the tree is empty).
  int leaf_of(const Vec3& xD, const Vec3& xL) const;
  const Leaf& leaf(int i) const { return leaves_[size_t(i)]; }
  size_t num_leaves() const { return leaves_.size(); }
  size_t num_nodes() const { return nodes_.size(); }
  size_t num_samples_stored() const;
  // Normalised 6D coordinates in [0,1]^6 (the cube around the scene bounds).
  void normalise(const Vec3& xD, const Vec3& xL, float out[6]) const;
  float threshold() const { return threshold_; }

 private:
  struct BuildNode;
  std::unique_ptr<BuildNode> build_rec(std::vector<SubpathSample> s, int depth, const float lo[6],
                                       const float hi[6]) const;
  int flatten(BuildNode& b);

  std::vector<Node> nodes_;
  std::vector<Leaf> leaves_;
  Vec3 origin_{0.f};
  float scale_ = 1.f;   // 1 / cube side
  float threshold_ = 1.f;
  STreeConfig cfg_;
};

}  // namespace mpg
