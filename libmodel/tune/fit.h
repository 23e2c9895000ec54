// Fitting the tissue laws to a measured nominal stress-strain curve
// (docs/tune.md).
//
// Bilinear law through the origin, continuous at the turning strain b:
//   sigma(e) = K1 e                   e <  b
//   sigma(e) = K1 b + K2 (e - b)      e >= b
// fitted by exact least squares over all four unknowns including b (two-phase
// regression, Hudson, J. Am. Stat. Assoc. 61, 1966): for each interval
// [e_j, e_{j+1}] of the data the problem with b inside it is linear once the
// partition of the points is fixed (segment 1 a line through the origin,
// segment 2 a free line, b where they meet); if that b falls inside the
// interval it is the interval's optimum, otherwise the optimum lies on an end
// of the interval (the residual is convex in (K1, K2, c = (K1 - K2) b), so the
// constrained minimum lies on the boundary), where b is fixed and the fit is
// a 2-parameter linear least squares. Scanning every interval and refining
// each this way gives the global minimum exactly, to round-off: an exactly
// bilinear curve is recovered exactly, wherever its turning strain falls
// between the samples.
#pragma once

#include <vector>

namespace orthosim::tune {

// Absolute least squares lets the stiff phase, whose stresses are K2/K1 times
// larger, set the whole fit; relative least squares (each residual divided by
// its measured stress) weighs both phases alike and is the default.
enum class FitWeighting { relative, absolute };

struct BilinearFit {
  double k1_pa = 0;           // slope below the turning strain (Pa)
  double turning_strain = 0;  // breakpoint b
  double k2_pa = 0;           // slope above it (Pa)
  double rms_pa = 0;          // root-mean-square residual (Pa, unweighted)
};

// strain: increasing, > 0 (the origin is implied: zero stress at zero strain);
// stress_pa: one per strain. Needs >= 3 samples; the turning strain is searched
// in [strain[0], strain[n-2]], so that the first phase holds the origin and at
// least one sample and the second at least two. Throws Error("", ...) on bad
// input (sizes, non-increasing or non-positive strains, non-finite values).
BilinearFit fit_bilinear(const std::vector<double>& strain, const std::vector<double>& stress_pa,
                         FitWeighting weighting = FitWeighting::relative);

// Linear law sigma = K e through the origin: K = sum(e sigma) / sum(e^2).
// Needs >= 1 sample with strain > 0.
double fit_linear(const std::vector<double>& strain, const std::vector<double>& stress_pa);

}  // namespace orthosim::tune
