/* The real-time iteration of fvin_mpc.control.rti.RealTimeMPC: its one loop, which the Python class drives
 * through ctypes and a robot links as it is. Every piece of the math is in the CasADi functions generated as
 * C (fvc_model.c: rti_linearize_blocks, rti_predict, rti_feedback, rti_apply; fvc_goal.c); this file is the
 * orchestration: the cold multi-start, the warm iterations, the preparation, the fallback, the restart and the
 * disturbance estimate. Iteration counts and wall-clock budgets (FVC_COLD_BUDGET_S, FVC_BUDGET_S; the monotonic
 * clock) bound a call. */
#define _POSIX_C_SOURCE 199309L
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "fvin_controller.h"
#include "fvc_config.h"
#include "fvc_model.h"
#if FVC_FREE_GOAL_GUESS
#include "fvc_goal.h"
#endif

#define N FVC_N
#define NS FVC_NS
#define M FVC_M
/* The state's blocks (fvin_mpc.core.blocks), as the generated block table gives them (fvc_config.h):
 * every position first, then every rate; fvc_quaternions[] the first entry of each unit quaternion,
 * fvc_angular[] the angular rates, fvc_hinges[] each hinge angle, FVC_ATTITUDE the one body attitude's
 * quaternion (and FVC_ATTITUDE_OMEGA its rate) where the state has exactly one, else -1. */
#define RS FVC_NPOS               /* first rate entry */
#define NR (NS - RS)              /* rates */
#define QS FVC_ATTITUDE
#define OM FVC_ATTITUDE_OMEGA

enum { LIN_H, LIN_HN, LIN_G, LIN_GN, LIN_AB, LIN_GAPS, LIN_COST, LIN_J, LIN_POINTS, LIN_COUNT };
/* Which Jacobians a linearization keeps from the last one (RTIOptions.relinearize_every): none, the last one's
 * where they stand (a further iteration on the same plan: renewed where its nodes moved, or all where every item
 * is renewed every time: fvc_renewed_further), or moved one item earlier (the shifted plan: renewed also where
 * fvc_relinearized says). */
enum { RENEW_ALL, KEEP_SAME, KEEP_SHIFTED };

struct fvc_controller {
    double X[(N + 1) * NS], U[N * M];        /* the plan */
    double CX[(N + 1) * NS], CU[N * M];      /* a cold guess being improved */
    double BX[(N + 1) * NS], BU[N * M];      /* the best cold plan */
    double NX_[(N + 1) * NS], NU[N * M];     /* an iteration's result */
    double ref[(N + 1) * NS], scales[N], u_s[N * M];
    double u_goal[M], d[M], limit[M];
    double p[FVC_NP];                        /* the model parameters (fvc_set_parameters) */
    double K[M * FVC_ND * N], k[M * N];       /* the prepared QP's Riccati gains (FVC_PREPARED_FEEDBACK) */
    double pred_rates[NR], pred_inverse[M * NR]; /* the last one-step prediction (column-major inverse) */
    double x0[NS];                           /* the measured state of the call under way (fvc_measure) */
    double start;                            /* when that call began (monotonic clock, s) */
    double cold_costs[3];                    /* each first guess's score on the last cold call (NaN: not tried) */
    int have_plan, prepared, have_prediction, pending_prediction, measured;
    double sent_x[NS], sent_u[M];            /* the last call's state and control, for the prediction */
    double time;
    double *lin[LIN_COUNT];
    double kept[FVC_KEPT_ITEMS * FVC_KEPT_ITEM];  /* the Jacobians a linearization may keep, as it reads them, */
    double kept_points[FVC_KEPT_ITEMS * FVC_KEPT_POINT];  /* and where they were computed */
    int jacobians_on_plan;                        /* lin[LIN_J] is the plan's (RealTimeMPC._plan_jacobians) */
    /* CasADi work memory, shared by the three functions */
    const casadi_real **arg;
    casadi_real **res;
    casadi_int *iw;
    casadi_real *w;
    fvc_status status;
};

static const char *guess_names[] = {"goal", "rollout+", "rollout-"};

void fvc_dims(int *ns, int *nd, int *m, int *n) { *ns = NS; *nd = FVC_ND; *m = M; *n = N; }
double fvc_step_size(void) { return FVC_STEP_SIZE; }
const char *fvc_cold_guess_name(int index) { return index >= 0 && index < 3 ? guess_names[index] : "none"; }

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

static double now_s(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static casadi_int out_size(const casadi_int *sp) { return sp[0] * sp[1]; } /* every output is dense */

/* u_s,k = clip(s_k u_goal − d): the control that holds the reference in the corrected model (reference_window) */
static void targets(fvc_controller *c) {
    for (int k = 0; k < N; k++)
        for (int j = 0; j < M; j++)
            c->u_s[k * M + j] = clip(c->scales[k] * c->u_goal[j] - c->d[j], fvc_torque_low[j], fvc_torque_high[j]);
}

/* ------------------------------------------------------------------ generated calls */
/* The last linearization's items (FVC_KEPT_ITEMS of `size` numbers) as the next reads them: where they stand, or
 * moved one item earlier with the last one repeated (rti.shifted_items). */
static void keep_items(double *to, const double *last, int size, int shifted) {
    if (shifted) {
        memcpy(to, last + size, sizeof(double) * (FVC_KEPT_ITEMS - 1) * size);
        memcpy(to + (FVC_KEPT_ITEMS - 1) * size, last + (FVC_KEPT_ITEMS - 1) * size, sizeof(double) * size);
    } else {
        memcpy(to, last, sizeof(double) * FVC_KEPT_ITEMS * size);
    }
}

static void call_linearize(fvc_controller *c, double *X, double *U, int keep) {
    if (FVC_IMPLICIT) {
        /* Both ends of a stage on one sheet of S³ (RealTimeMPC._linearize_at): flip every node after a sign change. */
        double turns[N];
        int any = 0;
        for (int k = 0; k < N; k++) {
            double t = 0.0;
            for (int i = 0; i < 4; i++) t += X[k * NS + QS + i] * X[(k + 1) * NS + QS + i];
            turns[k] = t;
            any |= t < 0.0;
        }
        if (any) {
            double sign = 1.0;
            for (int k = 1; k <= N; k++) {
                if (turns[k - 1] < 0.0) sign = -sign;
                for (int i = 0; i < 4; i++) X[k * NS + QS + i] *= sign;
            }
        }
    }
    targets(c);
    const double *renewed = fvc_all_renewed;
    /* RealTimeMPC.prepare / _improve: shifted_items; relinearize_every = 1 renews every item, nothing to copy */
    if (keep != RENEW_ALL && c->jacobians_on_plan && FVC_RELINEARIZE_EVERY > 1) {
        keep_items(c->kept, c->lin[LIN_J], FVC_KEPT_ITEM, keep == KEEP_SHIFTED);
        keep_items(c->kept_points, c->lin[LIN_POINTS], FVC_KEPT_POINT, keep == KEEP_SHIFTED);
        renewed = keep == KEEP_SHIFTED ? fvc_relinearized : fvc_renewed_further;  /* RealTimeMPC._linearize_at */
    } else {
        memcpy(c->kept_points, fvc_no_points, sizeof c->kept_points);
    }
    c->arg[0] = X; c->arg[1] = U; c->arg[2] = c->ref; c->arg[3] = c->d; c->arg[4] = c->u_s; c->arg[5] = c->p;
    c->arg[6] = c->kept; c->arg[7] = c->kept_points; c->arg[8] = renewed;
    for (int i = 0; i < LIN_COUNT; i++) c->res[i] = c->lin[i];
    rti_linearize_blocks(c->arg, c->res, c->iw, c->w, 0);
    c->jacobians_on_plan = keep != RENEW_ALL;
}

static void call_predict(fvc_controller *c, const double *x, const double *u, double *next, double *b,
                         double *residual, double *inverse) {
    c->arg[0] = x; c->arg[1] = u; c->arg[2] = c->p;
    c->res[0] = next; c->res[1] = b; c->res[2] = residual; c->res[3] = inverse;
    rti_predict(c->arg, c->res, c->iw, c->w, 0);
}

static int all_finite(const double *v, int count) {
    for (int i = 0; i < count; i++)
        if (!isfinite(v[i])) return 0;
    return 1;
}

/* One SQP iteration (RealTimeMPC._iterate_riccati): the new plan into NX_, NU; 0 if not finite. */
static int iterate(fvc_controller *c, const double *X, const double *U, const double *x0) {
    double step, mu;
    c->arg[0] = X; c->arg[1] = U; c->arg[2] = x0;
    for (int i = 0; i < LIN_GAPS + 1; i++) c->arg[3 + i] = c->lin[i];
    c->res[0] = c->NX_; c->res[1] = c->NU; c->res[2] = &step; c->res[3] = &mu; c->res[4] = 0; c->res[5] = 0;
    rti_feedback(c->arg, c->res, c->iw, c->w, 0);
    c->status.last_step = step;
    c->status.qp_mu = mu;
    return all_finite(c->NX_, (N + 1) * NS) && all_finite(c->NU, N * M);
}

/* The prepared feedback's preparation (RealTimeMPC.prepare, feedback="prepared"): the QP at the plan's own
 * first state, keeping its last Riccati gains for the call. */
static void prepare_gains(fvc_controller *c) {
    double step, mu;
    c->arg[0] = c->X; c->arg[1] = c->U; c->arg[2] = c->X;
    for (int i = 0; i < LIN_GAPS + 1; i++) c->arg[3 + i] = c->lin[i];
    c->res[0] = c->NX_; c->res[1] = c->NU; c->res[2] = &step; c->res[3] = &mu; c->res[4] = c->K; c->res[5] = c->k;
    rti_feedback(c->arg, c->res, c->iw, c->w, 0);
    c->status.qp_mu = mu;
}

/* The prepared feedback's call (RealTimeMPC._apply_prepared): the gains applied to the measured x0, the
 * new plan into NX_, NU; 0 if not finite. */
static int apply_prepared(fvc_controller *c, const double *x0) {
    double step;
    c->arg[0] = c->X; c->arg[1] = c->U; c->arg[2] = x0; c->arg[3] = c->K; c->arg[4] = c->k;
    c->arg[5] = c->lin[LIN_AB]; c->arg[6] = c->lin[LIN_GAPS];
    c->res[0] = c->NX_; c->res[1] = c->NU; c->res[2] = &step;
    rti_apply(c->arg, c->res, c->iw, c->w, 0);
    c->status.last_step = step;
    return all_finite(c->NX_, (N + 1) * NS) && all_finite(c->NU, N * M);
}

/* Up to `iterations` iterations on the plan (X, U) in place: the first always, each further one while the last
 * step was not below the tolerance and the last iteration's duration still fits before `deadline` (monotonic
 * clock, s; the budget's end sets status.budget). Returns the iterations done; *failed when the first gave no
 * finite plan (X, U unchanged). */
static int improve(fvc_controller *c, double *X, double *U, const double *x0, int iterations, int linearized,
                   int keep, double deadline, int *failed) {
    int done = 0;
    double last = 0.0;
    *failed = 0;
    while (done < iterations) {
        if (done > 0) {
            if (c->status.last_step < FVC_TOL) break;
            if (now_s() + last > deadline) {
                c->status.budget = 1;
                break;
            }
        }
        double begin = now_s();
        if (!linearized) call_linearize(c, X, U, keep);
        linearized = 0;
        if (!iterate(c, X, U, x0)) {
            *failed = done == 0;
            return done;
        }
        memcpy(X, c->NX_, sizeof c->NX_);
        memcpy(U, c->NU, sizeof c->NU);
        done++;
        last = now_s() - begin;
    }
    return done;
}

/* ------------------------------------------------------------------ cold start (MPC._first_guess) */
static void goal_guess(fvc_controller *c, const double *x0, double *X, double *U) {
#if FVC_FREE_GOAL_GUESS
    targets(c);  /* a free body: the generated geodesic to the reference (rti_goal_guess) */
    c->arg[0] = x0; c->arg[1] = c->ref; c->arg[2] = c->u_s;
    c->res[0] = X; c->res[1] = U;
    rti_goal_guess(c->arg, c->res, c->iw, c->w, 0);
    return;
#endif
    const double *q0 = x0 + QS;
    double goal[4], dot = 0.0;
    for (int i = 0; i < 4; i++) dot += q0[i] * fvc_goal_state[QS + i];
    for (int i = 0; i < 4; i++) goal[i] = (dot >= 0 ? 1.0 : -1.0) * fvc_goal_state[QS + i];
    double cosine = 0.0;
    for (int i = 0; i < 4; i++) cosine += q0[i] * goal[i];
    double angle = acos(clip(cosine, -1.0, 1.0));
    int third = N / 3 > 1 ? N / 3 : 1;
    memset(X, 0, sizeof(double) * (N + 1) * NS);
    for (int k = 0; k <= N; k++) {
        double weight = clip((double)k / third, 0.0, 1.0);
        for (int i = 0; i < 4; i++)
            X[k * NS + QS + i] = angle < 1e-9 ? q0[i]
                : (sin((1 - weight) * angle) * q0[i] + sin(weight * angle) * goal[i]) / sin(angle);
    }
    memcpy(X, x0, sizeof(double) * NS);
    memset(U, 0, sizeof(double) * N * M);
    (void)c;
}

static void rollout_guess(fvc_controller *c, const double *x0, double sign, double *X, double *U) {
    double b[NR * M], residual, inverse[M * NR];
    for (int k = 0; k < N; k++)
        for (int j = 0; j < M; j++)
            U[k * M + j] = clip(sign * FVC_INITIAL_TORQUE_FRACTION * fvc_torque_high[j], fvc_torque_low[j],
                                fvc_torque_high[j]);
    memcpy(X, x0, sizeof(double) * NS);
    for (int k = 0; k < N; k++) call_predict(c, X + k * NS, U + k * M, X + (k + 1) * NS, b, &residual, inverse);
    for (int k = 1; k <= N; k++)
        for (int a = 0; a < FVC_NANGULAR; a++) {
            int i = fvc_angular[a];
            X[k * NS + i] = clip(X[k * NS + i], -FVC_OMEGA_BOUND, FVC_OMEGA_BOUND);
        }
}

static double score(fvc_controller *c, double *X, double *U) {
    call_linearize(c, X, U, RENEW_ALL);
    double gaps = 0.0;
    for (int i = 0; i < N * FVC_ND; i++) gaps += c->lin[LIN_GAPS][i] * c->lin[LIN_GAPS][i];
    return c->lin[LIN_COST][0] + 1e3 * gaps;
}

/* Each first guess in fvc_cold_order, improved by up to FVC_COLD_ITER iterations while the cold budget lasts; the
 * best by score is the plan. Past the budget a guess is still scored, un-iterated (a rollout is a plan of the
 * model, with no gaps): the budget must not decide which guess wins. */
static int cold_start(fvc_controller *c, const double *x0) {
    int iterations = 0, have_best = 0, failed;
    double best = 0.0, deadline = c->start + FVC_COLD_BUDGET_S;
    for (int g = 0; g < 3; g++) c->cold_costs[g] = NAN;
    for (int g = 0; g < FVC_N_COLD; g++) {
        int guess = fvc_cold_order[g];
        if (guess == 0) goal_guess(c, x0, c->CX, c->CU);
        else rollout_guess(c, x0, guess == 1 ? 1.0 : -1.0, c->CX, c->CU);
        if (g > 0 && now_s() > deadline) c->status.budget = 1;
        else iterations += improve(c, c->CX, c->CU, x0, FVC_COLD_ITER, 0, RENEW_ALL, deadline, &failed);
        double value = score(c, c->CX, c->CU);
        c->cold_costs[guess] = value;
        if (!have_best || value < best) {
            have_best = 1;
            best = value;
            c->status.cold_guess = guess;
            memcpy(c->BX, c->CX, sizeof c->CX);
            memcpy(c->BU, c->CU, sizeof c->CU);
        }
    }
    memcpy(c->X, c->BX, sizeof c->BX);
    memcpy(c->U, c->BU, sizeof c->BU);
    return iterations;
}

/* ------------------------------------------------------------------ disturbance estimate (DisturbanceEstimate) */
/* R(q) v for q = (w, x, y, z): v + 2w (u × v) + 2 u × (u × v), u the imaginary part. */
static void rotate(const double *q, const double *v, double *out) {
    const double *u = q + 1;
    double t[3] = {2.0 * (u[1] * v[2] - u[2] * v[1]), 2.0 * (u[2] * v[0] - u[0] * v[2]), 2.0 * (u[0] * v[1] - u[1] * v[0])};
    out[0] = v[0] + q[0] * t[0] + (u[1] * t[2] - u[2] * t[1]);
    out[1] = v[1] + q[0] * t[1] + (u[2] * t[0] - u[0] * t[2]);
    out[2] = v[2] + q[0] * t[2] + (u[0] * t[1] - u[1] * t[0]);
}

static void update_estimate(fvc_controller *c, const double *x0) {
    if (FVC_DISTURBANCE_GAIN == 0.0 || !c->have_prediction) return;
    double angle, speed = 0.0;
    if (FVC_FREE_AXIS) { /* the axis's directions at the state and the goal; the speed without the spin about it */
        double here[3], there[3], along = 0.0;
        rotate(x0 + QS, fvc_free_axis, here);
        rotate(c->ref + QS, fvc_free_axis, there);
        double cross[3] = {here[1] * there[2] - here[2] * there[1], here[2] * there[0] - here[0] * there[2],
                           here[0] * there[1] - here[1] * there[0]};
        angle = atan2(sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]),
                      here[0] * there[0] + here[1] * there[1] + here[2] * there[2]);
        for (int i = 0; i < 3; i++) along += fvc_free_axis[i] * x0[OM + i];
        for (int i = 0; i < 3; i++) {
            double w = x0[OM + i] - along * fvc_free_axis[i];
            speed = fabs(w) > speed ? fabs(w) : speed;
        }
    } else { /* DisturbanceEstimate.update: the largest attitude or hinge angle from the reference */
        angle = 0.0;
        for (int b = 0; b < FVC_NQUAT; b++) {
            int first = fvc_quaternions[b];
            double cosine = 0.0;
            for (int i = 0; i < 4; i++) cosine += x0[first + i] * c->ref[first + i];
            cosine = fabs(cosine) < 1.0 ? fabs(cosine) : 1.0;
            double turn = 2.0 * acos(cosine);
            angle = turn > angle ? turn : angle;
        }
        for (int b = 0; b < FVC_NHINGE; b++) {
            double difference = x0[fvc_hinges[b]] - c->ref[fvc_hinges[b]];
            double turn = fabs(atan2(sin(difference), cos(difference)));
            angle = turn > angle ? turn : angle;
        }
        for (int a = 0; a < FVC_NANGULAR; a++) {
            double w = fabs(x0[fvc_angular[a]]);
            speed = w > speed ? w : speed;
        }
    }
    if (angle > FVC_DISTURBANCE_REGION_RAD || speed > FVC_DISTURBANCE_REGION_SPEED) return;
    for (int j = 0; j < M; j++) {
        double step = 0.0;
        for (int i = 0; i < NR; i++) step += c->pred_inverse[j + i * M] * (x0[RS + i] - c->pred_rates[i]);
        c->d[j] = clip(c->d[j] + FVC_DISTURBANCE_GAIN * step, -c->limit[j], c->limit[j]);
    }
}

/* The model's prediction after the control just sent (with d), for the next estimate (MPC._predicted).
 * fvc_feedback only records its arguments: the step is computed after the control is out — in
 * fvc_prepare, or at the next call — since nothing in this period's control depends on it. */
static void complete_prediction(fvc_controller *c) {
    if (!c->pending_prediction) return;
    double applied[M], next[NS], b[NR * M], residual;
    for (int j = 0; j < M; j++) applied[j] = c->sent_u[j] + c->d[j];
    call_predict(c, c->sent_x, applied, next, b, &residual, c->pred_inverse);
    memcpy(c->pred_rates, next + RS, sizeof c->pred_rates);
    c->have_prediction = 1;
    c->pending_prediction = 0;
    c->status.step_residual = residual;
}

/* u_goal: the control that holds the goal at rest in the model (MPC._goal_control, 5 Newton steps from 0) */
static void goal_control(fvc_controller *c) {
    double x_goal[NS], next[NS], b[NR * M], residual, inverse[M * NR];
    memcpy(x_goal, fvc_goal_state, sizeof x_goal);
    for (int k = RS; k < NS; k++) x_goal[k] = 0.0;
    memset(c->u_goal, 0, sizeof c->u_goal);
    for (int it = 0; it < 5; it++) {
        call_predict(c, x_goal, c->u_goal, next, b, &residual, inverse);
        double change[M];
        for (int j = 0; j < M; j++) {
            change[j] = 0.0;
            for (int k = 0; k < NR; k++) change[j] += inverse[j + k * M] * next[RS + k];
        }
        for (int j = 0; j < M; j++) c->u_goal[j] -= change[j];
    }
}

/* ------------------------------------------------------------------ API */
fvc_controller *fvc_create(void) {
    fvc_controller *c = calloc(1, sizeof *c);
    if (c == NULL) return NULL;
    casadi_int sz_arg = 0, sz_res = 0, sz_iw = 0, sz_w = 0, a, r, i, w;
    rti_linearize_blocks_work(&a, &r, &i, &w);
    sz_arg = a > sz_arg ? a : sz_arg; sz_res = r > sz_res ? r : sz_res; sz_iw = i > sz_iw ? i : sz_iw; sz_w = w > sz_w ? w : sz_w;
    rti_predict_work(&a, &r, &i, &w);
    sz_arg = a > sz_arg ? a : sz_arg; sz_res = r > sz_res ? r : sz_res; sz_iw = i > sz_iw ? i : sz_iw; sz_w = w > sz_w ? w : sz_w;
    rti_feedback_work(&a, &r, &i, &w);
    sz_arg = a > sz_arg ? a : sz_arg; sz_res = r > sz_res ? r : sz_res; sz_iw = i > sz_iw ? i : sz_iw; sz_w = w > sz_w ? w : sz_w;
    rti_apply_work(&a, &r, &i, &w);
    sz_arg = a > sz_arg ? a : sz_arg; sz_res = r > sz_res ? r : sz_res; sz_iw = i > sz_iw ? i : sz_iw; sz_w = w > sz_w ? w : sz_w;
#if FVC_FREE_GOAL_GUESS
    rti_goal_guess_work(&a, &r, &i, &w);
#endif
    sz_arg = a > sz_arg ? a : sz_arg; sz_res = r > sz_res ? r : sz_res; sz_iw = i > sz_iw ? i : sz_iw; sz_w = w > sz_w ? w : sz_w;
    c->arg = calloc(sz_arg > 9 ? sz_arg : 9, sizeof *c->arg);
    c->res = calloc(sz_res > 7 ? sz_res : 7, sizeof *c->res);
    c->iw = calloc(sz_iw + 1, sizeof *c->iw);
    c->w = calloc(sz_w + 1, sizeof *c->w);
    int ok = c->arg && c->res && c->iw && c->w;
    for (int k = 0; k < LIN_COUNT && ok; k++) {
        c->lin[k] = calloc(out_size(rti_linearize_blocks_sparsity_out(k)), sizeof(double));
        ok = c->lin[k] != NULL;
    }
    if (!ok) {
        fvc_free(c);
        return NULL;
    }
    for (int k = 0; k <= N; k++) memcpy(c->ref + k * NS, fvc_goal_state, sizeof(double) * NS);
    for (int k = 0; k < N; k++) c->scales[k] = 1.0;
    for (int j = 0; j < M; j++) c->limit[j] = 0.5 * (fvc_torque_high[j] - fvc_torque_low[j]);
    memcpy(c->p, fvc_parameter_defaults, sizeof c->p);
    goal_control(c);
    fvc_reset(c);
    return c;
}

void fvc_free(fvc_controller *c) {
    if (c == NULL) return;
    for (int k = 0; k < LIN_COUNT; k++) free(c->lin[k]);
    free(c->arg); free(c->res); free(c->iw); free(c->w);
    free(c);
}

void fvc_reset(fvc_controller *c) {
    c->have_plan = c->prepared = c->have_prediction = c->pending_prediction = c->jacobians_on_plan = 0;
    c->measured = 0;
    for (int g = 0; g < 3; g++) c->cold_costs[g] = NAN;
    memset(c->d, 0, sizeof c->d);
    c->time = 0.0;
}

void fvc_complete(fvc_controller *c) { complete_prediction(c); }

void fvc_prepare(fvc_controller *c) {
    complete_prediction(c);
    if (!c->have_plan || c->prepared) return;
    double applied[M], last[NS], b[NR * M], residual, inverse[M * NR];
    for (int j = 0; j < M; j++) applied[j] = c->U[(N - 1) * M + j] + c->d[j];
    call_predict(c, c->X + N * NS, applied, last, b, &residual, inverse);
    memmove(c->X, c->X + NS, sizeof(double) * N * NS);
    memcpy(c->X + N * NS, last, sizeof last);
    for (int a = 0; a < FVC_NANGULAR; a++) {
        int i = fvc_angular[a];
        c->X[N * NS + i] = clip(c->X[N * NS + i], -FVC_OMEGA_BOUND, FVC_OMEGA_BOUND);
    }
    memmove(c->U, c->U + M, sizeof(double) * (N - 1) * M);
    call_linearize(c, c->X, c->U, KEEP_SHIFTED);
    if (FVC_PREPARED_FEEDBACK) prepare_gains(c);
    c->prepared = 1;
    c->status.prepares++;
}

int fvc_measure(fvc_controller *c, const double *x) {
    double norms[FVC_NQUAT > 0 ? FVC_NQUAT : 1];
    c->start = now_s();
    c->measured = 0;
    int bad = !all_finite(x, NS);
    for (int b = 0; b < FVC_NQUAT; b++) {
        double norm = 0.0;
        for (int i = 0; i < 4; i++) norm += x[fvc_quaternions[b] + i] * x[fvc_quaternions[b] + i];
        norms[b] = sqrt(norm);
        bad |= !(fabs(norms[b] - 1.0) <= 1e-3);
    }
    if (bad) {
        c->status.bad_states++;
        return FVC_BAD_STATE;
    }
    memcpy(c->x0, x, sizeof c->x0);
    /* A quaternion already unit to rounding is left as it is: dividing by a norm of 1 ± 1 ulp would
     * only add rounding. */
    for (int b = 0; b < FVC_NQUAT; b++)
        if (fabs(norms[b] - 1.0) > 4.0 * DBL_EPSILON)
            for (int i = 0; i < 4; i++) c->x0[fvc_quaternions[b] + i] /= norms[b];
    complete_prediction(c);
    c->status.calls++;
    c->status.cold_guess = -1;
    c->status.budget = 0;
    c->status.restarted = 0;
    update_estimate(c, c->x0);
    if (c->have_plan && !isinf(FVC_RESTART_SPEED)) {  /* a stale plan (the measured rates far from the
                                                        * prediction of now) starts cold */
        if (!c->prepared) fvc_prepare(c);
        for (int a = 0; a < FVC_NANGULAR; a++)
            if (fabs(c->x0[fvc_angular[a]] - c->X[fvc_angular[a]]) > FVC_RESTART_SPEED) c->have_plan = 0;
        if (!c->have_plan) {
            c->prepared = 0;
            c->status.restarted = 1;
        }
    }
    c->measured = 1;
    return c->have_plan ? FVC_RTI : FVC_COLD;
}

/* The call's end: the plan's first control, clipped, and what the next prediction needs. */
static int finish(fvc_controller *c, int status, double *u) {
    c->have_plan = 1;
    c->prepared = 0;
    c->measured = 0;
    for (int j = 0; j < M; j++) u[j] = clip(c->U[j], fvc_torque_low[j], fvc_torque_high[j]);
    memcpy(c->sent_x, c->x0, sizeof c->x0);
    memcpy(c->sent_u, u, sizeof c->sent_u);
    c->pending_prediction = 1;
    c->time += FVC_STEP_SIZE;  /* the next measurement's time unless fvc_set_time says otherwise */
    c->status.status = status;
    return status;
}

int fvc_solve(fvc_controller *c, double *u) {
    if (!c->measured) return FVC_NOT_MEASURED;
    int status, failed = 0;
    if (!c->have_plan) {
        c->status.iterations = cold_start(c, c->x0);
        c->status.cold_calls++;
        status = FVC_COLD;
    } else {
        if (!c->prepared) fvc_prepare(c);
        if (FVC_PREPARED_FEEDBACK) {
            failed = !apply_prepared(c, c->x0);
            c->status.iterations = !failed;
            if (!failed) {
                memcpy(c->CX, c->NX_, sizeof c->NX_);
                memcpy(c->CU, c->NU, sizeof c->NU);
            }
        } else {
            memcpy(c->CX, c->X, sizeof c->X);
            memcpy(c->CU, c->U, sizeof c->U);
            c->status.iterations = improve(c, c->CX, c->CU, c->x0, FVC_MAX_ITER, 1, KEEP_SAME,
                                           c->start + FVC_BUDGET_S, &failed);
        }
        if (failed) {  /* the shifted previous plan */
            c->status.fallbacks++;
            status = FVC_FALLBACK;
        } else {
            memcpy(c->X, c->CX, sizeof c->X);
            memcpy(c->U, c->CU, sizeof c->U);
            status = FVC_RTI;
        }
    }
    return finish(c, status, u);
}

int fvc_solve_from(fvc_controller *c, const double *states, const double *controls, double *u) {
    if (!c->measured) return FVC_NOT_MEASURED;
    if (!all_finite(states, (N + 1) * NS) || !all_finite(controls, N * M)) return FVC_BAD_PLAN;
    int failed;
    memcpy(c->X, states, sizeof c->X);
    memcpy(c->U, controls, sizeof c->U);
    memcpy(c->X, c->x0, sizeof c->x0);  /* the plan starts at the measured state */
    for (int g = 0; g < 3; g++) c->cold_costs[g] = NAN;
    memcpy(c->CX, c->X, sizeof c->X);
    memcpy(c->CU, c->U, sizeof c->U);
    c->jacobians_on_plan = 0;
    c->status.iterations = improve(c, c->CX, c->CU, c->x0, 1, 0, RENEW_ALL, c->start, &failed);
    c->status.cold_calls++;
    if (!failed) {
        memcpy(c->X, c->CX, sizeof c->X);
        memcpy(c->U, c->CU, sizeof c->U);
    } else {
        c->status.fallbacks++;
    }
    return finish(c, failed ? FVC_FALLBACK : FVC_COLD, u);
}

int fvc_feedback(fvc_controller *c, const double *x, double *u) {
    int status = fvc_measure(c, x);
    return status < 0 ? status : fvc_solve(c, u);
}

void fvc_set_reference(fvc_controller *c, const double *states, const double *scales, int new_reference) {
    memcpy(c->ref, states, sizeof c->ref);
    memcpy(c->scales, scales, sizeof c->scales);
    if (new_reference) c->prepared = 0;
}

void fvc_set_time(fvc_controller *c, double t, int time_varying_reference) {
    if (fabs(t - c->time) > 1e-9) {
        c->have_prediction = c->pending_prediction = 0;
        if (time_varying_reference) c->prepared = 0;
    }
    c->time = t;
}

double fvc_time(const fvc_controller *c) { return c->time; }
void fvc_get_status(const fvc_controller *c, fvc_status *out) { *out = c->status; }
void fvc_get_plan(const fvc_controller *c, double *states, double *controls) {
    memcpy(states, c->X, sizeof c->X);
    memcpy(controls, c->U, sizeof c->U);
}
void fvc_get_disturbance(const fvc_controller *c, double *d) { memcpy(d, c->d, sizeof c->d); }
void fvc_set_disturbance(fvc_controller *c, const double *d) { memcpy(c->d, d, sizeof c->d); }
void fvc_get_goal_control(const fvc_controller *c, double *u_goal) { memcpy(u_goal, c->u_goal, sizeof c->u_goal); }
void fvc_get_cold_costs(const fvc_controller *c, double *costs) { memcpy(costs, c->cold_costs, sizeof c->cold_costs); }

int fvc_parameter_count(void) { return FVC_NP; }
const char *fvc_parameter_name(int index) { return index >= 0 && index < FVC_NP ? fvc_parameter_names[index] : NULL; }
void fvc_default_parameters(double *p) { memcpy(p, fvc_parameter_defaults, sizeof fvc_parameter_defaults); }
void fvc_get_parameters(const fvc_controller *c, double *p) { memcpy(p, c->p, sizeof c->p); }

int fvc_set_parameters(fvc_controller *c, const double *p) {
    if (!FVC_PARAMETRIC) return FVC_NOT_PARAMETRIC;
    if (!all_finite(p, FVC_NP)) return FVC_BAD_PARAMETERS;
    /* The prediction after the control already sent is the old model's: finish it before the model
     * changes. */
    complete_prediction(c);
    memcpy(c->p, p, sizeof c->p);
    goal_control(c);
    c->jacobians_on_plan = 0;  /* computed with the old parameters: the next linearization renews them all */
    return 0;
}
