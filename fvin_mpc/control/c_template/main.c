/* An example loop: the controller driven by its own model as the plant (replace the stand-in plant by
 * the robot's measurement and actuation), timed with the monotonic clock — the C loop's own latency,
 * nothing of Python in it. Build with `make`, run `./example [periods]`. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "fvin_controller.h"
#include "fvc_config.h"

static double now_us(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return 1e6 * (double)t.tv_sec + 1e-3 * (double)t.tv_nsec;
}

static int ascending(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* the q-quantile of values[0..count) (sorts them) */
static double quantile(double *values, int count, double q) {
    qsort(values, (size_t)count, sizeof *values, ascending);
    return values[(int)(q * (count - 1) + 0.5)];
}

int main(int argc, char **argv) {
    int ns, nd, m, n, periods = argc > 1 ? atoi(argv[1]) : 100;
    if (periods < 2) periods = 2;
    fvc_dims(&ns, &nd, &m, &n);
    fvc_controller *controller = fvc_create();
    double *feedback_us = malloc(sizeof(double) * periods), *period_us = malloc(sizeof(double) * periods);
    if (controller == NULL || feedback_us == NULL || period_us == NULL) {
        fprintf(stderr, "out of memory\n");
        return 1;
    }
    double x[FVC_NS], u[FVC_M], states[(FVC_N + 1) * FVC_NS], controls[FVC_N * FVC_M], p[FVC_NP];
    for (int i = 0; i < ns; i++) x[i] = fvc_example_state[i];
    /* the model parameters (run-time inputs; an adaptation would fvc_set_parameters new values) */
    fvc_get_parameters(controller, p);
    printf("%d model parameters:", fvc_parameter_count());
    for (int i = 0; i < fvc_parameter_count() && i < 4; i++) printf(" %s=%g", fvc_parameter_name(i), p[i]);
    printf("%s\n", fvc_parameter_count() > 4 ? " ..." : "");
    for (int k = 0; k < periods; k++) {
        double start = now_us();
        int status = fvc_feedback(controller, x, u);
        double sent = now_us();
        if (status < 0) {
            fprintf(stderr, "period %d: fvc_feedback refused the state (status %d)\n", k, status);
            return 1;
        }
        /* ... send u to the actuators here ... */
        fvc_prepare(controller);
        feedback_us[k] = sent - start;
        period_us[k] = now_us() - start;
        /* stand-in plant: the plan's next state (the model's prediction under u) */
        fvc_get_plan(controller, states, controls);
        for (int i = 0; i < ns; i++) x[i] = states[ns + i];
        if (k < 3) printf("period %d: status %d, u[0] = % .6f, feedback %.1f us\n", k, status, u[0], feedback_us[k]);
    }
    fvc_status status;
    fvc_get_status(controller, &status);
    printf("calls=%ld cold=%ld fallbacks=%ld prepares=%ld\n", status.calls, status.cold_calls, status.fallbacks,
           status.prepares);
    double cold = period_us[0];
    /* warm periods only: the first is the cold start */
    printf("cold first period %.0f us; warm feedback median %.1f us, p99 %.1f us; warm period median %.1f us, "
           "p99 %.1f us (step %.0f us)\n", cold, quantile(feedback_us + 1, periods - 1, 0.5),
           quantile(feedback_us + 1, periods - 1, 0.99), quantile(period_us + 1, periods - 1, 0.5),
           quantile(period_us + 1, periods - 1, 0.99), 1e6 * FVC_STEP_SIZE);
    free(feedback_us);
    free(period_us);
    fvc_free(controller);
    return 0;
}
