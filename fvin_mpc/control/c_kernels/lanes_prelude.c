/* What a lane kernel (fvin_mpc.control.lane_kernel) computes with: four stages in the four lanes of a vector.

   A lane kernel is CasADi's straight-line scalar C for one stage with every scalar made a vector of FVL_LANES
   doubles (GCC's and Clang's vector extension): one instruction stream evaluates four stages. Each operation is
   the scalar one in every lane -- +, -, *, / and sqrt are IEEE operations, the same in a lane as alone -- except
   tanh, which is computed here on whole vectors (fvl_tanh below): with libm's scalar tanh, four calls a
   vector, a learned ball joint's stage took 3.1-3.4 us in lanes; with this one, 1.35-1.43 us. Included once
   per translation unit (fvc_kernels.c holds every kernel of a controller). */

#ifndef FVL_PRELUDE
#define FVL_PRELUDE

#include <math.h>

#ifndef casadi_real
#define casadi_real double
#endif
#ifndef casadi_int
#define casadi_int long long int
#endif

#if !defined(__GNUC__) && !defined(__clang__)
#error "lane kernels use the GCC/Clang vector extension; build with gcc or clang, or set RTIOptions.stage_lanes='off'"
#endif

#define FVL_LANES 4
typedef double fvl_vec __attribute__((vector_size(8 * FVL_LANES)));
typedef long long fvl_int __attribute__((vector_size(8 * FVL_LANES)));
typedef unsigned long long fvl_uint __attribute__((vector_size(8 * FVL_LANES)));

/* A constant in every lane. (Not 0 + c: that turns -0.0 into +0.0.) */
static inline fvl_vec fvl_splat(double c) { fvl_vec v = {c, c, c, c}; return v; }
/* CasADi's logical values are the reals 1 and 0; a vector comparison gives the masks -1 and 0. */
static inline fvl_vec fvl_bool(fvl_int mask) { return __builtin_convertvector(-mask, fvl_vec); }
static inline fvl_vec fvl_blend(fvl_int mask, fvl_vec a, fvl_vec b) {
  return (fvl_vec)((mask & (fvl_int)a) | (~mask & (fvl_int)b));
}
/* (c ? a : 0) of CasADi's if_else, lane by lane: the lanes where c is 0 take exactly 0, whatever a holds. */
static inline fvl_vec fvl_select(fvl_vec c, fvl_vec a, fvl_vec b) { return fvl_blend(c != 0, a, b); }
static inline fvl_vec fvl_not(fvl_vec a) { return fvl_bool(a == 0); }
static inline fvl_vec fvl_lt(fvl_vec a, fvl_vec b) { return fvl_bool(a < b); }
static inline fvl_vec fvl_le(fvl_vec a, fvl_vec b) { return fvl_bool(a <= b); }
static inline fvl_vec fvl_eq(fvl_vec a, fvl_vec b) { return fvl_bool(a == b); }
static inline fvl_vec fvl_ne(fvl_vec a, fvl_vec b) { return fvl_bool(a != b); }
static inline fvl_vec fvl_and(fvl_vec a, fvl_vec b) { return fvl_bool((a != 0) & (b != 0)); }
static inline fvl_vec fvl_or(fvl_vec a, fvl_vec b) { return fvl_bool((a != 0) | (b != 0)); }
static inline fvl_vec fvl_casadi_sq(fvl_vec a) { return a * a; }
static inline fvl_vec fvl_casadi_fabs(fvl_vec a) { return (fvl_vec)((fvl_int)a & ~(fvl_int)fvl_splat(-0.0)); }

/* The rest lane by lane, with the scalar function CasADi's code calls: the same results to the bit. */
#define FVL_LANEWISE1(name, f)                                                                              \
  static inline fvl_vec name(fvl_vec a) {                                                                  \
    fvl_vec r;                                                                                             \
    int lane;                                                                                              \
    for (lane = 0; lane < FVL_LANES; ++lane) r[lane] = f(a[lane]);                                         \
    return r;                                                                                              \
  }
#define FVL_LANEWISE2(name, f)                                                                              \
  static inline fvl_vec name(fvl_vec a, fvl_vec b) {                                                       \
    fvl_vec r;                                                                                             \
    int lane;                                                                                              \
    for (lane = 0; lane < FVL_LANES; ++lane) r[lane] = f(a[lane], b[lane]);                                \
    return r;                                                                                              \
  }
static inline double fvl_sign1(double a) { return a < 0 ? -1. : a > 0 ? 1. : a; } /* CasADi's casadi_sign */
FVL_LANEWISE1(fvl_sqrt, sqrt)
FVL_LANEWISE1(fvl_exp, exp)
FVL_LANEWISE1(fvl_log, log)
FVL_LANEWISE1(fvl_sin, sin)
FVL_LANEWISE1(fvl_cos, cos)
FVL_LANEWISE1(fvl_tan, tan)
FVL_LANEWISE1(fvl_asin, asin)
FVL_LANEWISE1(fvl_acos, acos)
FVL_LANEWISE1(fvl_atan, atan)
FVL_LANEWISE1(fvl_sinh, sinh)
FVL_LANEWISE1(fvl_cosh, cosh)
FVL_LANEWISE1(fvl_floor, floor)
FVL_LANEWISE1(fvl_ceil, ceil)
FVL_LANEWISE1(fvl_erf, erf)
FVL_LANEWISE1(fvl_log1p, log1p)
FVL_LANEWISE1(fvl_expm1, expm1)
FVL_LANEWISE1(fvl_casadi_log1p, log1p) /* C99's, as CasADi's own helpers */
FVL_LANEWISE1(fvl_casadi_expm1, expm1)
FVL_LANEWISE1(fvl_casadi_sign, fvl_sign1)
FVL_LANEWISE2(fvl_casadi_fmax, fmax)
FVL_LANEWISE2(fvl_casadi_fmin, fmin)
FVL_LANEWISE2(fvl_atan2, atan2)
FVL_LANEWISE2(fvl_pow, pow)
FVL_LANEWISE2(fvl_fmod, fmod)

/* tanh on whole vectors: tanh |x| = e / (e + 2) with e = expm1(2|x|), the sign put back; 1 from |x| > 22 (where
   tanh is 1 in double precision: 1 - tanh(22) < 2^-60). expm1(z) = 2^k (expm1(r) + 1) - 1 with z = k ln 2 + r,
   |r| <= ln 2 / 2 (ln 2 in two parts, so k ln 2 is exact to 2^-80), expm1(r) its Taylor polynomial to r^13 (the
   remainder below 2^-56 of it). Within 4 units in the last place of libm's tanh (tests/test_lane_kernel.py:
   300,000 points, and 4 million in a one-off check); NaN stays NaN, -0 stays -0. */
static inline fvl_vec fvl_tanh(fvl_vec x) {
  const fvl_int sign = (fvl_int)fvl_splat(-0.0);
  const fvl_vec y = (fvl_vec)((fvl_int)x & ~sign);
  const fvl_vec z = 2.0 * fvl_blend(y > 22.0, fvl_splat(22.0), y); /* NaN > 22 is false: NaN goes on */
  const fvl_int k = __builtin_convertvector(z * 1.4426950408889634074 + 0.5, fvl_int); /* z >= 0: rounded */
  const fvl_vec kf = __builtin_convertvector(k, fvl_vec);
  const fvl_vec r = (z - kf * 6.93147180369123816490e-01) - kf * 1.90821492927058770002e-10;
  fvl_vec p = fvl_splat(1.0 / 6227020800.0); /* 1/13! */
  p = p * r + 1.0 / 479001600.0;
  p = p * r + 1.0 / 39916800.0;
  p = p * r + 1.0 / 3628800.0;
  p = p * r + 1.0 / 362880.0;
  p = p * r + 1.0 / 40320.0;
  p = p * r + 1.0 / 5040.0;
  p = p * r + 1.0 / 720.0;
  p = p * r + 1.0 / 120.0;
  p = p * r + 1.0 / 24.0;
  p = p * r + 1.0 / 6.0;
  p = p * r + 0.5;
  p = r + r * r * p; /* expm1(r) */
  const fvl_vec two_k = (fvl_vec)(((fvl_uint)k + 1023) << 52); /* unsigned: a NaN's k shifts without UB */
  const fvl_vec e = two_k * p + (two_k - 1.0);
  const fvl_vec t = e / (e + 2.0);
  return (fvl_vec)((fvl_int)t | ((fvl_int)x & sign));
}

#endif /* FVL_PRELUDE */
