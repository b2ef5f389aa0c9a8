/*
 * The contract between one example model (physics only) and the shared FMI 2.0
 * Model-Exchange glue in fmi2_glue.c (the standard's API and state machine, written once).
 *
 * Each model folder holds:
 *   config.h  - MODEL_IDENTIFIER, MODEL_GUID, NX (continuous states), NZ (event indicators),
 *               the value-reference enum and `typedef struct {...} ModelData;`
 *   model.c   - the functions declared below, and nothing about FMI call order.
 *   modelDescription.xml
 *
 * The glue owns one ModelInstance per fmi2Instantiate (no global state), calls the model
 * functions in the order the standard allows, and turns wrong-state calls into fmi2Error
 * with a logged message.
 */
#ifndef FMUBUILDER_EXAMPLE_MODEL_H
#define FMUBUILDER_EXAMPLE_MODEL_H

#include <stdbool.h>
#include <stddef.h>
#include "fmi2Functions.h"
#include "config.h"

typedef enum {
    STATE_START_AND_END = 1 << 0,
    STATE_INSTANTIATED = 1 << 1,
    STATE_INITIALIZATION_MODE = 1 << 2,
    STATE_EVENT_MODE = 1 << 3,
    STATE_CONTINUOUS_TIME_MODE = 1 << 4,
    STATE_TERMINATED = 1 << 5,
    STATE_ERROR = 1 << 6,
    STATE_FATAL = 1 << 7
} ModelState;

typedef struct ModelInstance {
    char *instanceName;
    fmi2CallbackFunctions callbacks;
    bool loggingOn;
    ModelState state;
    double time;
    /* From fmi2SetupExperiment (startTime 0, no stop time if it is not called). */
    double startTime;
    bool stopTimeDefined;
    double stopTime;
    /* Event bookkeeping the model fills in model_event_update / model_initialize. */
    bool newDiscreteStatesNeeded;
    bool terminateSimulation;
    bool nominalsOfContinuousStatesChanged;
    bool valuesOfContinuousStatesChanged;
    /* The glue clears the four flags above before each model_event_update; the next time
     * event persists until the model changes it. */
    bool nextEventTimeDefined;
    double nextEventTime;
    ModelData data; /* no pointers: FMU state snapshots are plain copies */
} ModelInstance;

/* Physics, implemented by each model.c. Values are SI doubles; integers and booleans
 * go through the typed accessors. A getter/setter returns fmi2Error for an unknown
 * value reference (the glue logs it). */
void model_set_start_values(ModelInstance *m);
/* Called at fmi2ExitInitializationMode: compute initial discrete values and the first
 * time event. */
void model_initialize(ModelInstance *m);
/* Called by fmi2NewDiscreteStates in event mode: update discrete states, reset
 * continuous states if needed, set the event flags and the next time event. */
void model_event_update(ModelInstance *m);

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value);
fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value);
fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value);
fmi2Status model_set_integer(ModelInstance *m, fmi2ValueReference vr, int value);
fmi2Status model_get_boolean(ModelInstance *m, fmi2ValueReference vr, bool *value);
fmi2Status model_set_boolean(ModelInstance *m, fmi2ValueReference vr, bool value);

void model_get_continuous_states(const ModelInstance *m, double x[]);
void model_set_continuous_states(ModelInstance *m, const double x[]);
void model_get_derivatives(ModelInstance *m, double dx[]);
void model_get_event_indicators(ModelInstance *m, double z[]);

/* Optional: a model that defines HAS_DIRECTIONAL_DERIVATIVE in config.h implements
 * this (d unknown / d known, both real value references) and declares
 * providesDirectionalDerivative="true" in its modelDescription.xml. */
fmi2Status model_get_partial_derivative(ModelInstance *m, fmi2ValueReference unknown,
                                        fmi2ValueReference known, double *partial);

/* Optional: a model that defines HAS_STEP_EVENT in config.h implements this; it is
 * called from fmi2CompletedIntegratorStep and returns true to request event mode (it may
 * also set m->terminateSimulation). Do not declare completedIntegratorStepNotNeeded="true". */
bool model_completed_integrator_step(ModelInstance *m);

/* Log through the importer's logger when logging is on (errors are always logged). */
void model_log(const ModelInstance *m, fmi2Status status, const char *category,
               const char *message, ...);

#endif
