// Biphasic springs and their decomposition into linear springs (paper §4.1).
//
// A biphasic spring (k1, turning length Lt, k2) at length L, rest length L0:
//   f(L) = k1 (L - L0)                          L <  Lt
//   f(L) = k1 (L - L0) + (k2 - k1) (L - Lt)     L >= Lt
// (libmodel/format/model.h). The emulated PPU offers linear springs only, so
// each biphasic spring becomes two linear springs in parallel: (k1, rest L0),
// always active, and (k2 - k1, rest Lt), slack (no force) below Lt. Their sum
// is f(L) exactly for every L >= 0, in tension and compression. A linear
// spring (k2 == k1) gives one linear spring.
#pragma once

#include "libmodel/format/model.h"

namespace orthosim::msm {

// The force (N, positive in tension) and its slope dF/dL (N/m) of one
// biphasic spring. Pure kernels shared by the builder's checks and the static
// solver (specimen.h).
inline double biphasic_force(double L, double L0, double k1, double k2, double Lt) {
  return k1 * (L - L0) + (L > Lt ? (k2 - k1) * (L - Lt) : 0.0);
}
inline double biphasic_slope(double L, double k1, double k2, double Lt) { return L > Lt ? k2 : k1; }
// Elastic energy (J): the integral of the force from L0 to L.
inline double biphasic_energy(double L, double L0, double k1, double k2, double Lt) {
  const double s = L - Lt;
  return 0.5 * k1 * (L - L0) * (L - L0) + (s > 0 ? 0.5 * (k2 - k1) * s * s : 0.0);
}

// The tissue law turned into spring parameters for springs of rest length L0
// and rule stiffness k_per_pa (m): k1 = K1 k_per_pa, k2 = K2 k_per_pa,
// Lt = L0 (1 + turning strain); a linear tissue gives k1 = k2 = K k_per_pa,
// Lt = L0.
struct SpringLaw {
  double k1_pa = 0, k2_pa = 0, turning_strain = 0;
};

// Fills lin_springs, lin_rest_length, lin_k, lin_damping and lin_slack of a
// layer from its springs, rest_length, k1, k2, turning_length and damping.
// The second spring's damping scales with sqrt(stiffness):
// c2 = c1 sqrt((k2 - k1) / k1), the same damping ratio for the same masses.
// Springs with k2 < k1 or turning_length < rest_length throw Error.
void decompose_biphasic(Layer& layer);

}  // namespace orthosim::msm
