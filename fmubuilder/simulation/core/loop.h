/* The event loop's state, shared by event_loop.c and sensitivity.c (not read by cffi). */
#ifndef FMUBUILDER_LOOP_H
#define FMUBUILDER_LOOP_H

#include "event_loop.h"

typedef struct Loop Loop;
typedef struct Sensitivity Sensitivity;

/* What a run with forward sensitivities (sensitivity.c) adds to the loop, called where the loop
 * steps, restarts its solver, records a row and leaves an event. The loop knows it only through
 * this table: sensitivity.c depends on the loop, not the other way round. */
typedef struct {
    Sensitivity *sens;
    double *layer_outputs;          /* where correct() keeps z and each layer's output */
    int (*step)(Loop *loop, double t, double h, const double *x);
    void (*restart)(Loop *loop, double t);
    int (*record)(Loop *loop, double t, const double *x, size_t row);
    void (*after_event)(Loop *loop, int values_changed);
} SensitivityHooks;

struct Loop {
    const CoreFmu *fmu;
    const CorePlan *plan;
    CoreResult *res;
    size_t n, nz;
    double eps;                     /* the engine's output tolerance: time_tolerance(start, scale) */
    /* the event sequence (events.EventSequence) */
    double t, next_event;
    int terminated, events_here, cuts_in_a_row;
    double *z, *z_end;              /* z: NULL without indicators */
    /* the engine's current state */
    double *x;
    /* the solver (solvers.Euler, RK4, DOPRI5) */
    double st, st_prev;
    double *sx, *sx_prev, *dx, *dx_prev, *x_new;
    int dx_current;
    double *stage, *k2, *k3, *k4, *interpolated;
    double h;                       /* DOPRI5: the proposed next step */
    double *K, *K_last, *abs_x, *abs_new, *Q;      /* DOPRI5: stages [7][n], |x|, dense output [n][4] */
    int stepped, dense_ready;
    /* locate's bracket */
    double *za, *zb, *z_trial, *wa, *wb;
    /* outputs and inputs */
    size_t i_out, i_bp, segment;
    double *input_values, *discrete_cache, *computed, *row;
    int *integers;
    int discrete_valid, continuous_mode;
    /* the correction's inputs, variables and layer buffers; derivatives for recorded columns */
    double *network_in, *network_a, *network_b, *variables, *recorded_dx;
    int derivative_columns;
    /* the point the instance was last put at: setting it again would change nothing */
    double held_t, *held_x;
    int held;
    double *raw_channel;            /* the FMU's derivative of each corrected state, as correct() found it */
    const SensitivityHooks *hooks;  /* forward sensitivities (sensitivity.c), or NULL */
    Sensitivity *sens;              /* their state: hooks->sens */
    double *layer_outputs;          /* where correct() keeps z and each layer's output, or NULL */
};

/* event_loop.c: the corrected derivatives at (t, x) (the instance put there); the FMU's variables
 * the correction reads are left in loop->variables, its inputs in loop->network_in. */
int loop_derivatives(Loop *loop, double t, const double *x, double *out);
/* event_loop.c: the FMU's own derivatives at (t, x) and the variables the correction reads. */
int loop_fmu_values(Loop *loop, double t, const double *x, double *der, double *variables);
/* event_loop.c: the recorded computed variables at (t, x), into loop->computed. */
int loop_computed(Loop *loop, double t, const double *x);
double loop_activated(int activation, double value);
/* The loop, with forward sensitivities (hooks) or without (NULL: core_run). */
int loop_run(const CoreFmu *fmu, const CorePlan *plan, CoreResult *result, const SensitivityHooks *hooks);

#endif
