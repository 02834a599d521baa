/* One backward stage of the real-time iteration's Riccati recursion, written for the vector units.

   The same function as fvin_mpc.control.rti.riccati_stage_function (which documents the math and is
   the reference this is tested against, tests/test_riccati_kernel.py), with CasADi's calling
   convention, so the generated feedback calls it in place of the generated stage:

       FVK_NAME(P, p, H, g, [A B], c, d, r) -> (P_prev, p_prev, K, k), all dense, column-major,

   P read from its upper triangle; H's upper triangle for Q and R and its lower-left block for S. The
   generated stage is straight-line scalar code; here the two products that make most of a stage,
   P [A B] and [A B]^T (P [A B]), run as loops over columns of four doubles. Included after a prelude
   that defines FVK_NAME, FVK_ND (n_delta) and FVK_M (m), and FVK_N for the whole backward sweep over N stages
   instead of one stage (what the feedback calls); compiled with -O3, where GCC unrolls the loops. */

#include <stddef.h>

#ifndef casadi_real
#define casadi_real double
#endif
#ifndef casadi_int
#define casadi_int long long int
#endif

#define FVK_S (FVK_ND + FVK_M)
#define FVK_PAD(n) (((n) + 3) / 4 * 4)
#define FVK_NP FVK_PAD(FVK_ND)
#define FVK_SP FVK_PAD(FVK_S)
#define FVK_CAT2(a, b) a##b
#define FVK_CAT(a, b) FVK_CAT2(a, b)

#if defined(__GNUC__) || defined(__clang__)
typedef double fvk_v4 __attribute__((vector_size(32), aligned(32)));
#define FVK_ALIGNED __attribute__((aligned(32)))
#else
#define FVK_ALIGNED
#endif

/* out = start + sum_e coefficient_e rows_e over n4 groups of four doubles (aligned), the sum kept in registers:
   the loop the products run. start may be out; rows_e = rows + e * stride, coefficient_e = coefficients[e * step]. */
static inline void fvk_combine(double *out, const double *start, const double *rows, int stride,
                               const double *coefficients, int step, int count, int n4) {
#if defined(__GNUC__) || defined(__clang__)
  fvk_v4 sum[FVK_SP / 4];
  int i, e;
  _Pragma("GCC unroll 16") for (i = 0; i < n4; ++i) sum[i] = ((const fvk_v4 *)start)[i];
  for (e = 0; e < count; ++e) {
    const fvk_v4 *row = (const fvk_v4 *)(rows + e * stride);
    const double a = coefficients[e * step];
    _Pragma("GCC unroll 16") for (i = 0; i < n4; ++i) sum[i] += row[i] * a;
  }
  _Pragma("GCC unroll 16") for (i = 0; i < n4; ++i) ((fvk_v4 *)out)[i] = sum[i];
#else
  int i, e;
  for (i = 0; i < 4 * n4; ++i) {
    double t = start[i];
    for (e = 0; e < count; ++e) t += rows[e * stride + i] * coefficients[e * step];
    out[i] = t;
  }
#endif
}

/* fvk_combine for two outputs over the same rows: two independent chains of multiply-adds per group, where one
   chain waits on each multiply-add's latency (a stage ran 1.4x faster so) */
static inline void fvk_combine_pair(double *out0, double *out1, const double *start0, const double *start1,
                                    const double *rows, int stride, const double *coefficients0,
                                    const double *coefficients1, int step, int count, int n4) {
#if defined(__GNUC__) || defined(__clang__)
  fvk_v4 sum0[FVK_SP / 4], sum1[FVK_SP / 4];
  int i, e;
  _Pragma("GCC unroll 16") for (i = 0; i < n4; ++i) {
    sum0[i] = ((const fvk_v4 *)start0)[i];
    sum1[i] = ((const fvk_v4 *)start1)[i];
  }
  for (e = 0; e < count; ++e) {
    const fvk_v4 *row = (const fvk_v4 *)(rows + e * stride);
    const double a0 = coefficients0[e * step], a1 = coefficients1[e * step];
    _Pragma("GCC unroll 16") for (i = 0; i < n4; ++i) {
      sum0[i] += row[i] * a0;
      sum1[i] += row[i] * a1;
    }
  }
  _Pragma("GCC unroll 16") for (i = 0; i < n4; ++i) {
    ((fvk_v4 *)out0)[i] = sum0[i];
    ((fvk_v4 *)out1)[i] = sum1[i];
  }
#else
  fvk_combine(out0, start0, rows, stride, coefficients0, step, count, n4);
  fvk_combine(out1, start1, rows, stride, coefficients1, step, count, n4);
#endif
}

static void fvk_stage(const double *P, const double *p, const double *H, const double *g, const double *AB,
                      const double *c, const double *d, const double *r, double *P_prev, double *p_prev, double *K,
                      double *k) {
  enum { ND = FVK_ND, M = FVK_M, S = FVK_S, NP = FVK_NP, SP = FVK_SP };
  double Pf[ND][NP] FVK_ALIGNED;   /* P, full, by columns (rows padded with zeros) */
  double PAB[S][NP] FVK_ALIGNED;   /* P [A B], by columns */
  double ABr[ND][SP] FVK_ALIGNED;  /* the rows of [A B] (padded) */
  double W[S][SP] FVK_ALIGNED;     /* H + [A B]^T P [A B], by columns */
  double pivot[M], U[M][M], Y[ND][M], Zt[M][NP] FVK_ALIGNED, pc[NP] FVK_ALIGNED, w_u[M];
  int i, j, a, b, e;
  /* (the copies in ranges, without conditions: a condition in these loops made GCC emit masked vector code
     that cost as much as the products) */
  for (j = 0; j < ND; ++j) {
    for (i = 0; i <= j; ++i) Pf[j][i] = P[i + ND * j];
    for (i = j + 1; i < ND; ++i) Pf[j][i] = P[j + ND * i];
    for (i = ND; i < NP; ++i) Pf[j][i] = 0.0;
  }
  for (e = 0; e < ND; ++e) {
    for (j = 0; j < S; ++j) ABr[e][j] = AB[e + ND * j];
    for (j = S; j < SP; ++j) ABr[e][j] = 0.0;
  }
  double zeros[NP] FVK_ALIGNED = {0.0};
  for (j = 0; j + 1 < S; j += 2)
    fvk_combine_pair(PAB[j], PAB[j + 1], zeros, zeros, Pf[0], NP, AB + ND * j, AB + ND * (j + 1), 1, ND, NP / 4);
  if (S % 2) fvk_combine(PAB[S - 1], zeros, Pf[0], NP, AB + ND * (S - 1), 1, ND, NP / 4);
  for (j = 0; j < S; ++j) {
    /* column j of H as the generated stage reads it: Q and R from their upper triangles, S from the lower-left
       block (so S^T from there too) */
    double *column = W[j];
    const int block = j < ND ? ND : S;  /* where column j's diagonal block ends */
    const int first = j < ND ? 0 : ND;  /* and starts */
    for (i = 0; i < first; ++i) column[i] = H[j + S * i];
    for (i = first; i <= j; ++i) column[i] = H[i + S * j];
    for (i = j + 1; i < block; ++i) column[i] = H[j + S * i];
    for (i = block; i < S; ++i) column[i] = H[i + S * j];
    for (i = S; i < SP; ++i) column[i] = 0.0;
  }
  for (j = 0; j + 1 < S; j += 2)
    fvk_combine_pair(W[j], W[j + 1], W[j], W[j + 1], ABr[0], SP, PAB[j], PAB[j + 1], 1, ND, SP / 4);
  if (S % 2) fvk_combine(W[S - 1], W[S - 1], ABr[0], SP, PAB[S - 1], 1, ND, SP / 4);
  /* gram = R + diag(d) + B^T P B = U^T D U, U unit upper triangular */
  for (a = 0; a < M; ++a) {
    double s = W[ND + a][ND + a] + d[a];
    for (e = 0; e < a; ++e) s -= U[e][a] * U[e][a] * pivot[e];
    pivot[a] = s;
    for (b = a + 1; b < M; ++b) {
      double t = W[ND + b][ND + a];
      for (e = 0; e < a; ++e) t -= U[e][a] * U[e][b] * pivot[e];
      U[a][b] = t / s;
    }
  }
  /* Y = U^-T cross (cross = S + B^T P A), K = -U^-1 D^-1 Y */
  for (j = 0; j < ND; ++j)
    for (a = 0; a < M; ++a) {
      double t = W[j][ND + a];
      for (e = 0; e < a; ++e) t -= U[e][a] * Y[j][e];
      Y[j][a] = t;
    }
  for (j = 0; j < ND; ++j)
    for (a = M - 1; a >= 0; --a) {
      double t = -Y[j][a] / pivot[a];
      for (e = a + 1; e < M; ++e) t -= U[a][e] * K[e + M * j];
      K[a + M * j] = t;
    }
  /* P_prev = Q + A^T P A - Y^T D^-1 Y by columns, its upper triangle mirrored */
  for (a = 0; a < M; ++a) {
    for (i = 0; i < ND; ++i) Zt[a][i] = Y[i][a] / pivot[a];
    for (i = ND; i < NP; ++i) Zt[a][i] = 0.0;
  }
  for (j = 0; j < ND; ++j) {
    double column[NP] FVK_ALIGNED, minus_y[M];
    for (a = 0; a < M; ++a) minus_y[a] = -Y[j][a];
    fvk_combine(column, W[j], Zt[0], NP, minus_y, 1, M, NP / 4);
    for (i = 0; i <= j; ++i) P_prev[i + ND * j] = P_prev[j + ND * i] = column[i];
  }
  /* the vectors: pc = P c + p; [A B]^T pc; k = -gram^-1 r~ with r~ = r + B^T pc; p_prev = g + A^T pc - Z^T U^-T r~ */
  double transposed[SP] FVK_ALIGNED, zeros_s[SP] FVK_ALIGNED = {0.0}, minus_w[M];
  for (i = 0; i < ND; ++i) pc[i] = p[i];
  for (i = ND; i < NP; ++i) pc[i] = 0.0;
  fvk_combine(pc, pc, Pf[0], NP, c, 1, ND, NP / 4);
  fvk_combine(transposed, zeros_s, ABr[0], SP, pc, 1, ND, SP / 4);
  for (a = 0; a < M; ++a) {
    double t = r[a] + transposed[ND + a];
    for (e = 0; e < a; ++e) t -= U[e][a] * w_u[e];
    w_u[a] = t;
  }
  for (a = M - 1; a >= 0; --a) {
    double t = -w_u[a] / pivot[a];
    for (e = a + 1; e < M; ++e) t -= U[a][e] * k[e];
    k[a] = t;
  }
  for (i = 0; i < ND; ++i) transposed[i] += g[i];  /* g + A^T pc, then less Z^T U^-T r~ */
  for (a = 0; a < M; ++a) minus_w[a] = -w_u[a];
  fvk_combine(pc, transposed, Zt[0], NP, minus_w, 1, M, NP / 4);
  for (i = 0; i < ND; ++i) p_prev[i] = pc[i];
}

#ifndef FVK_N
/* The stage alone: FVK_NAME(P, p, H, g, [A B], c, d, r) -> (P_prev, p_prev, K, k). */
int FVK_NAME(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, int mem) {
  (void)iw, (void)w, (void)mem;
  fvk_stage(arg[0], arg[1], arg[2], arg[3], arg[4], arg[5], arg[6], arg[7], res[0], res[1], res[2], res[3]);
  return 0;
}
#else
/* The whole backward sweep over FVK_N stages, in place and in the stages' own order (no reversed copies, no
   cost-to-go handed from call to call): FVK_NAME(P_N, p_N, H (s x sN), g (s x N), [A B] (nd x sN), c (nd x N),
   d (m x N), r (m x N)) -> (K (m x nd N), k (m x N)), stage k's blocks at its own columns. */
int FVK_NAME(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, int mem) {
  enum { ND = FVK_ND, M = FVK_M, S = FVK_S };
  double cost_to_go[2][ND * ND + ND];
  int k, next = 0;
  (void)iw, (void)w, (void)mem;
  for (k = 0; k < ND * ND; ++k) cost_to_go[0][k] = arg[0][k];
  for (k = 0; k < ND; ++k) cost_to_go[0][ND * ND + k] = arg[1][k];
  for (k = FVK_N - 1; k >= 0; --k, next ^= 1) {
    const double *later = cost_to_go[next];
    double *earlier = cost_to_go[next ^ 1];
    fvk_stage(later, later + ND * ND, arg[2] + S * S * k, arg[3] + S * k, arg[4] + ND * S * k, arg[5] + ND * k,
              arg[6] + M * k, arg[7] + M * k, earlier, earlier + ND * ND, res[0] + M * ND * k, res[1] + M * k);
  }
  return 0;
}
#endif

/* What casadi.external reads to call the kernel from a shared library (the generated code calls FVK_NAME
   directly): eight inputs, four outputs (the sweep: two), dense. */
#ifndef FVK_N
static const casadi_int FVK_CAT(FVK_NAME, _sp)[12][3] = {
    {FVK_ND, FVK_ND, 1}, {FVK_ND, 1, 1}, {FVK_S, FVK_S, 1}, {FVK_S, 1, 1}, {FVK_ND, FVK_S, 1}, {FVK_ND, 1, 1},
    {FVK_M, 1, 1}, {FVK_M, 1, 1},
    {FVK_ND, FVK_ND, 1}, {FVK_ND, 1, 1}, {FVK_M, FVK_ND, 1}, {FVK_M, 1, 1}};
#define FVK_N_OUT 4
#else
static const casadi_int FVK_CAT(FVK_NAME, _sp)[10][3] = {
    {FVK_ND, FVK_ND, 1}, {FVK_ND, 1, 1}, {FVK_S, FVK_S * FVK_N, 1}, {FVK_S, FVK_N, 1}, {FVK_ND, FVK_S * FVK_N, 1},
    {FVK_ND, FVK_N, 1}, {FVK_M, FVK_N, 1}, {FVK_M, FVK_N, 1},
    {FVK_M, FVK_ND * FVK_N, 1}, {FVK_M, FVK_N, 1}};
#define FVK_N_OUT 2
#endif
casadi_int FVK_CAT(FVK_NAME, _n_in)(void) { return 8; }
casadi_int FVK_CAT(FVK_NAME, _n_out)(void) { return FVK_N_OUT; }
const casadi_int *FVK_CAT(FVK_NAME, _sparsity_in)(casadi_int i) {
  return i >= 0 && i < 8 ? FVK_CAT(FVK_NAME, _sp)[i] : NULL;
}
const casadi_int *FVK_CAT(FVK_NAME, _sparsity_out)(casadi_int i) {
  return i >= 0 && i < FVK_N_OUT ? FVK_CAT(FVK_NAME, _sp)[8 + i] : NULL;
}
#undef FVK_N_OUT
