/* The floor of a table look-up of the escape angle, in C: benchmarks/floor.py compiles
   this at run time and calls it through ctypes, one thread, on the table `trace` builds.

   Phi on both sides of the shadow edge: cubic Hermite in tau = log|alpha - alpha_sh| on
   uniform knots. The escaping side (alpha > alpha_sh) holds knots [0, n0) of `phi` and
   `slope`, the captured side knots [n0, n0 + n1); each side starts at its own tau0 and
   steps by its own dtau. One log a ray, and no branch: gcc vectorises the loop, the
   log through glibc's libmvec, with -ffast-math and -fopenmp-simd (the `omp simd`
   pragma), as long as tau0 and dtau are scalars in registers, not array reads.

   Below a side's first knot the cubic of its first interval is extrapolated (jaxlens
   continues the log law linearly there); no ray of the benchmark lies there.

   lookup_f64: double throughout; lookup_f32: float throughout (logf), for the float32
   table. Arguments: alpha[count] (radians), out[count] (radians), alpha_sh (radians),
   tau0_out, dtau_out, tau0_in, dtau_in (the sides' first knot and step in tau), phi and
   slope (dPhi/dtau) of both sides, n0 and n1 (knots a side, each >= 2). */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#define LOOKUP(NAME, REAL, LOG, FABS)                                                    \
  void NAME(const REAL *restrict alpha, REAL *restrict out, size_t count,               \
            REAL alpha_sh, REAL tau0_out, REAL dtau_out, REAL tau0_in, REAL dtau_in,    \
            const REAL *restrict phi, const REAL *restrict slope, int32_t n0,           \
            int32_t n1) {                                                               \
    const REAL inv0 = (REAL)1 / dtau_out, inv1 = (REAL)1 / dtau_in;                     \
    _Pragma("omp simd")                                                                 \
    for (size_t k = 0; k < count; k++) {                                                \
      REAL gap = alpha[k] - alpha_sh;                                                   \
      int side = gap < 0;                                                               \
      REAL x = (LOG(FABS(gap)) - (side ? tau0_in : tau0_out)) * (side ? inv1 : inv0);   \
      int32_t last = side ? n1 - 2 : n0 - 2;                                            \
      int32_t i = (int32_t)x;                                                           \
      i = i < 0 ? 0 : (i > last ? last : i);                                            \
      REAL t = x - (REAL)i, h = side ? dtau_in : dtau_out;                              \
      i += side ? n0 : 0;                                                               \
      REAL p0 = phi[i], p1 = phi[i + 1], m0 = slope[i] * h, m1 = slope[i + 1] * h;      \
      REAL t2 = t * t, t3 = t2 * t;                                                     \
      out[k] = (2 * t3 - 3 * t2 + 1) * p0 + (t3 - 2 * t2 + t) * m0 +                    \
               (3 * t2 - 2 * t3) * p1 + (t3 - t2) * m1;                                 \
    }                                                                                   \
  }

LOOKUP(lookup_f64, double, log, fabs)
LOOKUP(lookup_f32, float, logf, fabsf)
