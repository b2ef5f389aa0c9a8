/* The compiled simulation core: the event loop of FMI 2.0 Model Exchange for one instance, with a
 * fixed-step solver (explicit Euler or classical RK4), state-event location, time, step and input
 * events, event iteration and the output grid. Python (core/__init__.py) initialises the instance,
 * hands it over with a plan, and gets arrays back; nothing runs in Python per step.
 *
 * The semantics are those of simulation/events.py (EventSequence, locate) driven as
 * simulation/engine.py drives it, operation for operation, so both loops give the same numbers to
 * the bit. This header is read by cffi as well: declarations only, no macros. */
#ifndef FMUBUILDER_EVENT_LOOP_H
#define FMUBUILDER_EVENT_LOOP_H

#include <stddef.h>
#include <stdint.h>

/* The FMI 2.0 functions the loop calls, as plain function pointers (fmi2Status is an int,
 * fmi2Boolean an int, fmi2ValueReference an unsigned int). */
typedef int (*core_set_time_fn)(void *, double);
typedef int (*core_set_vector_fn)(void *, const double *, size_t);
typedef int (*core_get_vector_fn)(void *, double *, size_t);
typedef int (*core_set_real_fn)(void *, const unsigned int *, size_t, const double *);
typedef int (*core_get_real_fn)(void *, const unsigned int *, size_t, double *);
typedef int (*core_set_int_fn)(void *, const unsigned int *, size_t, const int *);
typedef int (*core_get_int_fn)(void *, const unsigned int *, size_t, int *);
typedef int (*core_completed_step_fn)(void *, int, int *, int *);
typedef int (*core_mode_fn)(void *);

typedef struct {
    int newDiscreteStatesNeeded;
    int terminateSimulation;
    int nominalsOfContinuousStatesChanged;
    int valuesOfContinuousStatesChanged;
    int nextEventTimeDefined;
    double nextEventTime;
} core_event_info;

typedef int (*core_new_discrete_states_fn)(void *, core_event_info *);

/* Which FMI call a breadcrumb code or an error names (index into CoreFmu.call_codes). */
typedef enum {
    CALL_SET_TIME, CALL_SET_CONTINUOUS_STATES, CALL_GET_DERIVATIVES, CALL_GET_EVENT_INDICATORS,
    CALL_GET_CONTINUOUS_STATES, CALL_SET_REAL, CALL_GET_REAL, CALL_SET_INTEGER, CALL_GET_INTEGER,
    CALL_SET_BOOLEAN, CALL_GET_BOOLEAN, CALL_COMPLETED_INTEGRATOR_STEP, CALL_ENTER_EVENT_MODE,
    CALL_ENTER_CONTINUOUS_TIME_MODE, CALL_NEW_DISCRETE_STATES, CALL_COUNT
} core_call;

/* One initialised instance in continuous-time mode and how to call it. */
typedef struct {
    void *component;
    core_set_time_fn set_time;
    core_set_vector_fn set_continuous_states;
    core_get_vector_fn get_derivatives;
    core_get_vector_fn get_event_indicators;
    core_get_vector_fn get_continuous_states;
    core_set_real_fn set_real;
    core_get_real_fn get_real;
    core_set_int_fn set_integer;
    core_get_int_fn get_integer;
    core_set_int_fn set_boolean;
    core_get_int_fn get_boolean;
    core_completed_step_fn completed_integrator_step;
    core_mode_fn enter_event_mode;
    core_mode_fn enter_continuous_time_mode;
    core_new_discrete_states_fn new_discrete_states;
    /* The crash breadcrumb (fmi/breadcrumb.py): +code in a call, -code after it; model time. A
     * supervisor's ping (ping_slot 1) is answered (0) after each call returns: the process is not
     * stuck in a call, though no Python code runs while the loop does. */
    int64_t *call_slot;
    int64_t *ping_slot;
    double *time_slot;
    int64_t call_codes[15];         /* breadcrumb code of each core_call */
} CoreFmu;

enum { CORE_EULER = 0, CORE_RK4 = 1, CORE_DOPRI5 = 2 };
/* A recorded column: a state, a variable that changes only at events, one computed from the state,
 * or a state derivative as the corrected system gives it. */
enum { COLUMN_STATE = 0, COLUMN_DISCRETE = 1, COLUMN_COMPUTED = 2, COLUMN_DERIVATIVE = 3 };
enum { SOURCE_STATE = 0, SOURCE_DERIVATIVE = 1, SOURCE_VARIABLE = 2 };
enum { ACTIVATION_NONE = 0, ACTIVATION_TANH = 1, ACTIVATION_SIGMOID = 2, ACTIVATION_RELU = 3 };
enum { BASIS_W = 0, BASIS_ABS = 1, BASIS_SIGNED_SQUARE = 2, BASIS_SQUARE = 3 };

/* A correction of some state derivatives, evaluated after each fmi2GetDerivatives (a NeuralFMU's
 * network, with a fitted base term):
 *     z = the inputs: states, the FMU's derivatives, FMU variables (read after the derivatives)
 *     out = dense layers over z (W row-major [rows][cols], + b, then the layer's activation)
 *     der[channel_k] = out_k + gate_fmu_k der[channel_k] (+ base, with one channel)
 *     base = term_gate (term_bias + the terms' sums, basis by basis: coefficient basis(z_i - center))
 * No layers: the channels keep the FMU's derivative plus the base. */
typedef struct {
    size_t n_inputs;
    const int *input_source;        /* SOURCE_* */
    const int *input_index;
    size_t n_variables;
    const unsigned int *variable_vrs;
    size_t n_layers;
    const int *layer_rows;
    const int *layer_cols;
    const int *layer_activation;    /* ACTIVATION_* after the affine map */
    const double *weights;          /* the layers' W, one after another */
    const double *biases;           /* the layers' b, one after another */
    size_t n_channels;
    const int *channel_state;
    const double *gate_fmu;
    size_t n_terms;                 /* grouped by basis, in BASIS_* order */
    const int *term_basis;
    const int *term_input;
    const double *term_center;
    const double *term_coefficient;
    double term_bias;
    double term_gate;               /* 0: no base */
} CoreCorrection;
enum { TYPE_REAL = 0, TYPE_INTEGER = 1, TYPE_BOOLEAN = 2 };

/* What to simulate, from where the initialisation left the instance. */
typedef struct {
    size_t n_states;
    size_t n_indicators;
    int solver;                     /* CORE_EULER, CORE_RK4 or CORE_DOPRI5 */
    double step_size;               /* the fixed step */
    double rtol, atol, max_step;    /* DOPRI5's */
    double start, stop;
    double time_scale;              /* events.time_scale(start, stop) */
    double relative_time_tolerance; /* events.RELATIVE_TIME_TOLERANCE */
    int max_events_at_one_time;     /* events.MAX_EVENTS_AT_ONE_TIME */
    int max_cuts_in_a_row;          /* events.MAX_CUT_STEPS_IN_A_ROW */
    const double *x0;               /* the states after initialisation */
    double next_event;              /* the next time event after initialisation (inf: none) */
    int needs_completed_step;
    int record_events;
    /* The output grid, and each recorded column: a state (index into x), a variable that changes
     * only at events (index into the discrete table) or one computed from the state (index into
     * the computed table). */
    size_t n_outputs;
    const double *output_times;
    size_t n_columns;
    const int *column_kind;
    const int *column_index;
    size_t n_discrete;
    const unsigned int *discrete_vrs;
    const int *discrete_types;      /* TYPE_* */
    size_t n_computed;
    const unsigned int *computed_vrs;
    /* Inputs: samples; continuous Real inputs (linear between samples, held outside, kinks at
     * the breakpoints); discrete ones (held, changed in event mode at input_event_times). */
    size_t n_samples;
    const double *sample_times;
    size_t n_continuous_inputs;
    const unsigned int *continuous_input_vrs;
    const double *continuous_values;    /* [n_samples][n_continuous_inputs] */
    const double *continuous_slopes;    /* [n_samples - 1][n_continuous_inputs] */
    size_t n_breakpoints;
    const double *breakpoints;          /* within (start, stop), sorted */
    size_t n_discrete_inputs;
    const unsigned int *discrete_input_vrs;
    const int *discrete_input_types;
    const double *discrete_values;      /* [n_samples][n_discrete_inputs] */
    size_t n_input_events;
    const double *input_event_times;
    const CoreCorrection *correction;   /* NULL: the FMU's own derivatives */
    int64_t max_rhs_evaluations;        /* the run's work: stop with CORE_WORK_LIMIT beyond it (0: none) */
} CorePlan;

enum { CORE_OK = 0, CORE_FMI_ERROR = 1, CORE_EVENT_STORM = 2, CORE_CHATTERING = 3, CORE_NO_MEMORY = 4,
       CORE_STEP_UNDERFLOW = 5, CORE_WORK_LIMIT = 6 };
enum { EVENT_TIME = 0, EVENT_STATE = 1, EVENT_STEP = 2 };

/* What a run gives back; the arrays are the core's (free them with core_free_result). */
typedef struct {
    int error;                      /* CORE_* */
    int failed_call;                /* core_call of a CORE_FMI_ERROR */
    int failed_status;              /* its fmi2Status */
    double error_time;
    double error_step;              /* the step size of a CORE_STEP_UNDERFLOW */
    double t;                       /* the time reached */
    double next_event;              /* the next time event pending there (inf: none) */
    int terminated;                 /* the model asked to stop */
    double *x;                      /* the states reached [n_states] */
    size_t n_rows;
    double *times;                  /* [n_rows] */
    double *rows;                   /* [n_rows][n_columns] */
    size_t n_events;
    double *event_times;
    int *event_kinds;               /* EVENT_* */
    int64_t steps, rejected_steps, rhs_evaluations, indicator_evaluations;
    int64_t time_events, state_events, step_events, event_iterations;
    size_t row_capacity, event_capacity;
} CoreResult;

int core_run(const CoreFmu *fmu, const CorePlan *plan, CoreResult *result);
void core_free_result(CoreResult *result);

/* The run of core_run with forward sensitivities of the states to the correction's parameters
 * (sensitivity.c): theta = each layer's W (row-major) and b, layer after layer, then the channels'
 * FMU gates (n_parameters in all). gradient [n_parameters] gets the sum over the recorded rows of
 * weights[row][column] d(value)/dtheta (weights [n_rows][n_columns], the rows as the run records
 * them, events' rows too; NULL: the run alone). resets: the events at which the FMU changed its
 * continuous states (their sensitivities are not followed). */
int core_gradient_run(const CoreFmu *fmu, const CorePlan *plan, const double *weights, size_t n_rows,
                      size_t n_parameters, double *gradient, int64_t *resets, CoreResult *result);

#endif
