/* Event corner cases that exported FMUs exhibit, on analytic trajectories. */
#ifndef EVENT_CORNER_CASES_CONFIG_H
#define EVENT_CORNER_CASES_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "event_corner_cases"
#define MODEL_GUID "{c3a1e7d2-6b58-4f0e-8d24-91f7a0b3c5e6}"

#define NX 2 /* sawtooth p, ramp r */
#define NZ 2 /* two indicators for the same relation p >= p_max */

#define HAS_STEP_EVENT

/* Value references, in the order of modelDescription.xml (index = vr + 1). */
typedef enum {
    VR_P = 0,
    VR_DER_P = 1,
    VR_R = 2,
    VR_DER_R = 3,
    VR_P_MAX = 4,
    VR_T_STEP = 5,
    VR_T_TERMINATE = 6,
    VR_STEP_EVENT_TIME = 7,
    VR_RESETS = 8,
    VR_START_TICKS = 9,
    VR_START_TICKS_SEEN = 10,
    VR_STEP_EVENT_DONE = 11
} ValueReference;

typedef struct {
    double p;               /* sawtooth state, der(p) = 1, reset to 0 at p_max [1] */
    double r;               /* ramp state, der(r) = +1 before the step event, -1 after [1] */
    double p_max;           /* reset threshold of p [1] */
    double t_step;          /* time from which the step event is requested [s] */
    double t_terminate;     /* time at which the model requests termination [s] */
    double step_event_time; /* when the step event was handled, -1 before [s] */
    int resets;             /* number of state events (resets of p) */
    int start_ticks;        /* time events handled at the start time */
    int start_ticks_seen;   /* copy of start_ticks, updated one event iteration later */
    bool step_event_done;   /* the step event has been handled */
    bool terminate_pending; /* t_terminate is the scheduled time event */
} ModelData;

#endif
