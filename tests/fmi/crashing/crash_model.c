/* The bouncing ball with a binary that misbehaves, for the crash-isolation tests.
 *
 * CRASH_MODE selects what happens: 1 segfault, 2 abort, 3 exit(0), 4 exit(3), 5 hang.
 * CRASH_IN_INSTANTIATE misbehaves in fmi2Instantiate (through model_set_start_values),
 * otherwise fmi2GetDerivatives misbehaves once the model time reaches CRASH_TIME. */
#include <stdlib.h>
#include <unistd.h>

#define model_set_start_values ball_set_start_values
#define model_get_derivatives ball_get_derivatives
#include "model.c"
#undef model_set_start_values
#undef model_get_derivatives

#ifndef CRASH_TIME
#define CRASH_TIME 0.5
#endif

static void misbehave(void) {
    switch (CRASH_MODE) {
    case 1: { volatile int *nowhere = NULL; *nowhere = 1; break; }
    case 2: abort();
    case 3: exit(0);
    case 4: exit(3);
    case 5: for (;;) sleep(1);
    }
}

void model_set_start_values(ModelInstance *m) {
#ifdef CRASH_IN_INSTANTIATE
    misbehave();
#endif
    ball_set_start_values(m);
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
#ifndef CRASH_IN_INSTANTIATE
    if (m->time >= CRASH_TIME) misbehave();
#endif
    ball_get_derivatives(m, dx);
}
