/* A sawtooth with a state event and a ramp turned by a step event that only a completed
 * integrator step requests; the completed steps are counted. */
#ifndef COMPLETED_STEPS_CONFIG_H
#define COMPLETED_STEPS_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "completed_steps"
#define MODEL_GUID "{5e0c2b7a-91d4-4f3e-a6b8-2c7d9e1f4a03}"

#define NX 2 /* sawtooth p, ramp r */
#define NZ 1 /* p - p_max */

#define HAS_STEP_EVENT

typedef enum {
    VR_P = 0,
    VR_DER_P = 1,
    VR_R = 2,
    VR_DER_R = 3,
    VR_P_MAX = 4,
    VR_T_STEP = 5,
    VR_STEPS = 6,
    VR_STEP_EVENT_TIME = 7
} ValueReference;

typedef struct {
    double p;               /* sawtooth, der(p) = 1, reset to 0 at p_max */
    double r;               /* ramp, der(r) = +1 before the step event, -1 after */
    double p_max;
    double t_step;          /* completed steps ending at or after it request the step event */
    double steps;           /* fmi2CompletedIntegratorStep calls so far */
    double step_event_time; /* when the step event was handled, -1 before */
    bool requested;         /* a completed step requested the step event */
    bool done;              /* the step event was handled */
} ModelData;

#endif
