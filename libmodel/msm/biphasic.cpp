#include "libmodel/msm/biphasic.h"

#include <cmath>

namespace orthosim::msm {

void decompose_biphasic(Layer& l) {
  const Eigen::Index n = l.springs.rows();
  Eigen::Index m = 0;
  for (Eigen::Index s = 0; s < n; ++s) {
    if (l.k2(s) < l.k1(s)) throw Error("", "biphasic spring with k2 < k1");
    if (l.turning_length(s) < l.rest_length(s)) throw Error("", "biphasic spring turning before its rest length");
    m += l.k2(s) > l.k1(s) ? 2 : 1;
  }
  l.lin_springs.resize(m, 2);
  l.lin_rest_length.resize(m);
  l.lin_k.resize(m);
  l.lin_damping.resize(m);
  l.lin_slack.resize(m);
  // every first-phase spring first (rows 0..n-1 mirror the springs), then the slack ones
  Eigen::Index r = n;
  for (Eigen::Index s = 0; s < n; ++s) {
    l.lin_springs.row(s) = l.springs.row(s);
    l.lin_rest_length(s) = l.rest_length(s);
    l.lin_k(s) = l.k1(s);
    l.lin_damping(s) = l.damping(s);
    l.lin_slack(s) = 0;
    if (l.k2(s) > l.k1(s)) {
      l.lin_springs.row(r) = l.springs.row(s);
      l.lin_rest_length(r) = l.turning_length(s);
      l.lin_k(r) = l.k2(s) - l.k1(s);
      l.lin_damping(r) = l.k1(s) > 0 ? l.damping(s) * std::sqrt((l.k2(s) - l.k1(s)) / l.k1(s)) : l.damping(s);
      l.lin_slack(r) = 1;
      ++r;
    }
  }
}

}  // namespace orthosim::msm
