/* An example loop: the controller driven by its own model as the plant (replace `plant_step` by the
 * robot's measurement and actuation). Build with `make`, run `./example [periods]`. */
#include <stdio.h>
#include <stdlib.h>

#include "fvin_controller.h"
#include "fvc_config.h"

int main(int argc, char **argv) {
    int ns, nd, m, n, periods = argc > 1 ? atoi(argv[1]) : 100;
    fvc_dims(&ns, &nd, &m, &n);
    fvc_controller *controller = fvc_create();
    if (controller == NULL) {
        fprintf(stderr, "fvc_create: out of memory\n");
        return 1;
    }
    double x[FVC_NS], u[FVC_M], states[(FVC_N + 1) * FVC_NS], controls[FVC_N * FVC_M];
    for (int i = 0; i < ns; i++) x[i] = fvc_example_state[i];
    for (int k = 0; k < periods; k++) {
        int status = fvc_feedback(controller, x, u);
        if (status < 0) {
            fprintf(stderr, "period %d: fvc_feedback refused the state (status %d)\n", k, status);
            return 1;
        }
        /* ... send u to the actuators here ... */
        fvc_prepare(controller);
        /* stand-in plant: the plan's next state (the model's prediction under u) */
        fvc_get_plan(controller, states, controls);
        for (int i = 0; i < ns; i++) x[i] = states[ns + i];
        printf("%d status=%d u0=% .6f\n", k, status, u[0]);
    }
    fvc_status status;
    fvc_get_status(controller, &status);
    printf("calls=%ld cold=%ld fallbacks=%ld prepares=%ld\n", status.calls, status.cold_calls, status.fallbacks,
           status.prepares);
    fvc_free(controller);
    return 0;
}
