/*
 * FMI 2.0 Model-Exchange API for any model that follows model.h.
 *
 * This file owns the standard's state machine: every fmi2 function first checks that
 * it may be called in the instance's current state, validates its arguments, and only
 * then calls into the model's physics. A call in the wrong state or with bad arguments
 * returns fmi2Error with a logged message and leaves the instance unchanged, so an
 * importer's mistake never crashes the process.
 *
 * All mutable data lives in the ModelInstance (allocated with the importer's
 * allocateMemory callback), so any number of instances can coexist in one process.
 */
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "model.h"

#ifndef NX
#error "config.h must define NX (number of continuous states)"
#endif
#ifndef NZ
#error "config.h must define NZ (number of event indicators)"
#endif

/* ---------------------------------------------------------------------------------------
 * Which states allow which call (FMI 2.0 standard, section 3.2.3, Model Exchange).
 */
#define ANY_MODE_AFTER_INIT_STARTED                                                         \
    (STATE_INITIALIZATION_MODE | STATE_EVENT_MODE | STATE_CONTINUOUS_TIME_MODE |            \
     STATE_TERMINATED | STATE_ERROR)

#define MASK_GET_VALUES ANY_MODE_AFTER_INIT_STARTED
#define MASK_SET_REAL                                                                       \
    (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE | STATE_EVENT_MODE |                    \
     STATE_CONTINUOUS_TIME_MODE)
#define MASK_SET_DISCRETE (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE | STATE_EVENT_MODE)
#define MASK_FMU_STATE (STATE_INSTANTIATED | ANY_MODE_AFTER_INIT_STARTED)
#define MASK_DEBUG_LOGGING (STATE_INSTANTIATED | ANY_MODE_AFTER_INIT_STARTED)
#define MASK_RESET (STATE_INSTANTIATED | ANY_MODE_AFTER_INIT_STARTED)
#define MASK_NOMINALS (STATE_INSTANTIATED | ANY_MODE_AFTER_INIT_STARTED)

static const char *state_name(ModelState state) {
    switch (state) {
    case STATE_START_AND_END: return "StartAndEnd";
    case STATE_INSTANTIATED: return "Instantiated";
    case STATE_INITIALIZATION_MODE: return "InitializationMode";
    case STATE_EVENT_MODE: return "EventMode";
    case STATE_CONTINUOUS_TIME_MODE: return "ContinuousTimeMode";
    case STATE_TERMINATED: return "Terminated";
    case STATE_ERROR: return "Error";
    case STATE_FATAL: return "Fatal";
    }
    return "Unknown";
}

/* ---------------------------------------------------------------------------------------
 * Logging and memory: always through the importer's callbacks.
 */
static void log_va(const ModelInstance *m, fmi2Status status, const char *category,
                   const char *message, va_list args) {
    char text[512];
    char escaped[2 * sizeof(text)];
    bool always = status == fmi2Error || status == fmi2Fatal;
    if (m == NULL || m->callbacks.logger == NULL || !(m->loggingOn || always)) {
        return;
    }
    vsnprintf(text, sizeof(text), message, args);
    /* The logger treats its message as a printf format. Passing the text itself with '%'
     * doubled (rather than "%s" plus an argument) also reads right in importers that
     * cannot format variadic arguments and print the format string as is. */
    size_t n = 0;
    for (const char *c = text; *c != '\0'; c++) {
        if (*c == '%') {
            escaped[n++] = '%';
        }
        escaped[n++] = *c;
    }
    escaped[n] = '\0';
    m->callbacks.logger(m->callbacks.componentEnvironment, m->instanceName, status, category,
                        escaped);
}

void model_log(const ModelInstance *m, fmi2Status status, const char *category,
               const char *message, ...) {
    va_list args;
    va_start(args, message);
    log_va(m, status, category, message, args);
    va_end(args);
}

static void *allocate(const ModelInstance *m, size_t size) {
    if (m->callbacks.allocateMemory != NULL) {
        return m->callbacks.allocateMemory(1, size);
    }
    return calloc(1, size);
}

static void release(const ModelInstance *m, void *pointer) {
    if (pointer == NULL) {
        return;
    }
    if (m->callbacks.freeMemory != NULL) {
        m->callbacks.freeMemory(pointer);
    } else {
        free(pointer);
    }
}

/* ---------------------------------------------------------------------------------------
 * Argument and state checks shared by all functions.
 */
static bool allowed_in_state(ModelInstance *m, int mask, const char *function) {
    if (m->state & mask) {
        return true;
    }
    model_log(m, fmi2Error, "logStatusError", "%s must not be called in state %s.", function,
              state_name(m->state));
    return false;
}

static bool not_null(ModelInstance *m, const void *pointer, const char *argument,
                     const char *function) {
    if (pointer != NULL) {
        return true;
    }
    model_log(m, fmi2Error, "logStatusError", "%s: argument %s must not be NULL.", function,
              argument);
    return false;
}

/* Arrays of length n may only be NULL when n == 0. */
static bool array_ok(ModelInstance *m, const void *array, size_t n, const char *argument,
                     const char *function) {
    return n == 0 || not_null(m, array, argument, function);
}

static bool size_matches(ModelInstance *m, size_t given, size_t expected, const char *argument,
                         const char *function) {
#ifdef REJECT_EMPTY_ARRAYS
    /* Some tools' FMUs answer the state and indicator calls with an error when the array is
     * empty; importers must not make them (test models build this switch). */
    if (given == 0) {
        model_log(m, fmi2Error, "logStatusError", "%s: called with %s = 0.", function, argument);
        return false;
    }
#endif
    if (given == expected) {
        return true;
    }
    model_log(m, fmi2Error, "logStatusError", "%s: %s is %zu but the model has %zu.", function,
              argument, given, expected);
    return false;
}

/* Casts the component and checks the call is allowed now; NULL means "return fmi2Error". */
static ModelInstance *checked(fmi2Component c, int mask, const char *function) {
    ModelInstance *m = (ModelInstance *)c;
    if (m == NULL) {
        return NULL;
    }
    return allowed_in_state(m, mask, function) ? m : NULL;
}

static void clear_event_flags(ModelInstance *m) {
    m->newDiscreteStatesNeeded = false;
    m->terminateSimulation = false;
    m->nominalsOfContinuousStatesChanged = false;
    m->valuesOfContinuousStatesChanged = false;
}

/* ---------------------------------------------------------------------------------------
 * Common functions: platform, logging, lifecycle.
 */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    static const char *const known[] = {"logEvents", "logStatusError"};
    ModelInstance *m = checked(c, MASK_DEBUG_LOGGING, "fmi2SetDebugLogging");
    if (m == NULL || !array_ok(m, categories, nCategories, "categories", "fmi2SetDebugLogging")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nCategories; i++) {
        bool found = false;
        for (size_t k = 0; k < sizeof(known) / sizeof(known[0]); k++) {
            found = found || (categories[i] != NULL && strcmp(categories[i], known[k]) == 0);
        }
        if (!found) {
            model_log(m, fmi2Error, "logStatusError",
                      "fmi2SetDebugLogging: unknown log category '%s'.",
                      categories[i] ? categories[i] : "(null)");
            return fmi2Error;
        }
    }
    m->loggingOn = loggingOn != fmi2False;
    return fmi2OK;
}

static void reset_to_start(ModelInstance *m) {
    m->state = STATE_INSTANTIATED;
    m->time = 0.0;
    m->startTime = 0.0;
    m->stopTimeDefined = false;
    m->stopTime = 0.0;
    clear_event_flags(m);
    m->nextEventTimeDefined = false;
    m->nextEventTime = 0.0;
    memset(&m->data, 0, sizeof(m->data));
    model_set_start_values(m);
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn) {
    ModelInstance probe; /* logs through the callbacks before the instance exists */
    (void)fmuResourceLocation;
    (void)visible;
    if (functions == NULL) {
        return NULL;
    }
    memset(&probe, 0, sizeof(probe));
    probe.callbacks = *functions;
    probe.instanceName = (char *)(instanceName ? instanceName : "?");
    if (instanceName == NULL || instanceName[0] == '\0') {
        model_log(&probe, fmi2Error, "logStatusError",
                  "fmi2Instantiate: instanceName must be a non-empty string.");
        return NULL;
    }
    if (fmuType != fmi2ModelExchange) {
        model_log(&probe, fmi2Error, "logStatusError",
                  "fmi2Instantiate: %s supports Model Exchange only, not Co-Simulation.",
                  MODEL_IDENTIFIER);
        return NULL;
    }
    if (fmuGUID == NULL || strcmp(fmuGUID, MODEL_GUID) != 0) {
        model_log(&probe, fmi2Error, "logStatusError",
                  "fmi2Instantiate: GUID '%s' does not match the model's '%s'.",
                  fmuGUID ? fmuGUID : "(null)", MODEL_GUID);
        return NULL;
    }

    ModelInstance *m = allocate(&probe, sizeof(ModelInstance));
    char *name = allocate(&probe, strlen(instanceName) + 1);
    if (m == NULL || name == NULL) {
        model_log(&probe, fmi2Error, "logStatusError", "fmi2Instantiate: out of memory.");
        release(&probe, m);
        release(&probe, name);
        return NULL;
    }
    memset(m, 0, sizeof(*m));
    strcpy(name, instanceName);
    m->instanceName = name;
    m->callbacks = *functions;
    m->loggingOn = loggingOn != fmi2False;
    reset_to_start(m);
    return m;
}

void fmi2FreeInstance(fmi2Component c) {
    ModelInstance *m = (ModelInstance *)c;
    if (m == NULL) {
        return;
    }
    /* Copy the callbacks first: they live inside the memory being released. */
    ModelInstance owner = *m;
    release(&owner, m->instanceName);
    release(&owner, m);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined,
                               fmi2Real tolerance, fmi2Real startTime,
                               fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    ModelInstance *m = checked(c, STATE_INSTANTIATED, "fmi2SetupExperiment");
    (void)toleranceDefined;
    (void)tolerance;
    if (m == NULL) {
        return fmi2Error;
    }
    if (stopTimeDefined && stopTime < startTime) {
        model_log(m, fmi2Error, "logStatusError",
                  "fmi2SetupExperiment: stopTime %g is before startTime %g.", stopTime,
                  startTime);
        return fmi2Error;
    }
    m->startTime = startTime;
    m->time = startTime;
    m->stopTimeDefined = stopTimeDefined != fmi2False;
    m->stopTime = stopTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    ModelInstance *m = checked(c, STATE_INSTANTIATED, "fmi2EnterInitializationMode");
    if (m == NULL) {
        return fmi2Error;
    }
    m->state = STATE_INITIALIZATION_MODE;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    ModelInstance *m = checked(c, STATE_INITIALIZATION_MODE, "fmi2ExitInitializationMode");
    if (m == NULL) {
        return fmi2Error;
    }
    clear_event_flags(m);
    m->nextEventTimeDefined = false;
    model_initialize(m);
    m->state = STATE_EVENT_MODE; /* Model Exchange continues in event mode. */
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    ModelInstance *m =
        checked(c, STATE_EVENT_MODE | STATE_CONTINUOUS_TIME_MODE, "fmi2Terminate");
    if (m == NULL) {
        return fmi2Error;
    }
    m->state = STATE_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    ModelInstance *m = checked(c, MASK_RESET, "fmi2Reset");
    if (m == NULL) {
        return fmi2Error;
    }
    reset_to_start(m);
    return fmi2OK;
}

/* ---------------------------------------------------------------------------------------
 * Getting and setting variable values.
 */
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    ModelInstance *m = checked(c, MASK_GET_VALUES, "fmi2GetReal");
    if (m == NULL || !array_ok(m, vr, nvr, "vr", "fmi2GetReal") ||
        !array_ok(m, value, nvr, "value", "fmi2GetReal")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nvr; i++) {
        if (model_get_real(m, vr[i], &value[i]) != fmi2OK) {
            model_log(m, fmi2Error, "logStatusError", "fmi2GetReal: no Real variable with vr=%u.",
                      vr[i]);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[]) {
    ModelInstance *m = checked(c, MASK_SET_REAL, "fmi2SetReal");
    if (m == NULL || !array_ok(m, vr, nvr, "vr", "fmi2SetReal") ||
        !array_ok(m, value, nvr, "value", "fmi2SetReal")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nvr; i++) {
        if (model_set_real(m, vr[i], value[i]) != fmi2OK) {
            model_log(m, fmi2Error, "logStatusError",
                      "fmi2SetReal: cannot set vr=%u to %g in state %s (not a settable Real "
                      "variable, or a value outside its valid range).",
                      vr[i], value[i], state_name(m->state));
            return fmi2Error;
        }
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Integer value[]) {
    ModelInstance *m = checked(c, MASK_GET_VALUES, "fmi2GetInteger");
    if (m == NULL || !array_ok(m, vr, nvr, "vr", "fmi2GetInteger") ||
        !array_ok(m, value, nvr, "value", "fmi2GetInteger")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nvr; i++) {
        int v = 0;
        if (model_get_integer(m, vr[i], &v) != fmi2OK) {
            model_log(m, fmi2Error, "logStatusError",
                      "fmi2GetInteger: no Integer variable with vr=%u.", vr[i]);
            return fmi2Error;
        }
        value[i] = v;
    }
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Integer value[]) {
    ModelInstance *m = checked(c, MASK_SET_DISCRETE, "fmi2SetInteger");
    if (m == NULL || !array_ok(m, vr, nvr, "vr", "fmi2SetInteger") ||
        !array_ok(m, value, nvr, "value", "fmi2SetInteger")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nvr; i++) {
        if (model_set_integer(m, vr[i], value[i]) != fmi2OK) {
            model_log(m, fmi2Error, "logStatusError",
                      "fmi2SetInteger: cannot set vr=%u to %d (not a settable Integer variable, "
                      "or a value outside its valid range).",
                      vr[i], value[i]);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Boolean value[]) {
    ModelInstance *m = checked(c, MASK_GET_VALUES, "fmi2GetBoolean");
    if (m == NULL || !array_ok(m, vr, nvr, "vr", "fmi2GetBoolean") ||
        !array_ok(m, value, nvr, "value", "fmi2GetBoolean")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nvr; i++) {
        bool v = false;
        if (model_get_boolean(m, vr[i], &v) != fmi2OK) {
            model_log(m, fmi2Error, "logStatusError",
                      "fmi2GetBoolean: no Boolean variable with vr=%u.", vr[i]);
            return fmi2Error;
        }
        value[i] = v ? fmi2True : fmi2False;
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[]) {
    ModelInstance *m = checked(c, MASK_SET_DISCRETE, "fmi2SetBoolean");
    if (m == NULL || !array_ok(m, vr, nvr, "vr", "fmi2SetBoolean") ||
        !array_ok(m, value, nvr, "value", "fmi2SetBoolean")) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nvr; i++) {
        if (model_set_boolean(m, vr[i], value[i] != fmi2False) != fmi2OK) {
            model_log(m, fmi2Error, "logStatusError",
                      "fmi2SetBoolean: cannot set vr=%u to %d (not a settable Boolean variable).",
                      vr[i], value[i]);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

/* The example models have no String variables: only empty requests succeed. */
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         fmi2String value[]) {
    ModelInstance *m = checked(c, MASK_GET_VALUES, "fmi2GetString");
    (void)value;
    if (m == NULL) {
        return fmi2Error;
    }
    if (nvr > 0) {
        model_log(m, fmi2Error, "logStatusError", "fmi2GetString: no String variable with vr=%u.",
                  vr ? vr[0] : 0u);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         const fmi2String value[]) {
    ModelInstance *m = checked(c, MASK_SET_DISCRETE, "fmi2SetString");
    (void)value;
    if (m == NULL) {
        return fmi2Error;
    }
    if (nvr > 0) {
        model_log(m, fmi2Error, "logStatusError", "fmi2SetString: no String variable with vr=%u.",
                  vr ? vr[0] : 0u);
        return fmi2Error;
    }
    return fmi2OK;
}

#ifdef FMU_STATE_UNSUPPORTED
/* ---------------------------------------------------------------------------------------
 * FMU state refused: compiled with FMU_STATE_UNSUPPORTED, the model behaves like the many FMUs
 * exported with canGetAndSetFMUstate="false" (every call is an error with a logged message).
 */
static fmi2Status fmu_state_refused(fmi2Component c, const char *function) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, function);
    if (m != NULL) {
        model_log(m, fmi2Error, "logStatusError",
                  "%s: this FMU does not support getting and setting its state.", function);
    }
    return fmi2Error;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)FMUstate;
    return fmu_state_refused(c, "fmi2GetFMUstate");
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    (void)FMUstate;
    return fmu_state_refused(c, "fmi2SetFMUstate");
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)FMUstate;
    return fmu_state_refused(c, "fmi2FreeFMUstate");
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)FMUstate;
    (void)size;
    return fmu_state_refused(c, "fmi2SerializedFMUstateSize");
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size) {
    (void)FMUstate;
    (void)serializedState;
    (void)size;
    return fmu_state_refused(c, "fmi2SerializeFMUstate");
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    (void)serializedState;
    (void)size;
    (void)FMUstate;
    return fmu_state_refused(c, "fmi2DeSerializeFMUstate");
}

#else
/* ---------------------------------------------------------------------------------------
 * FMU state: ModelData holds no pointers, so a snapshot is a plain copy.
 */
typedef struct {
    ModelState state;
    double time;
    double startTime;
    bool stopTimeDefined;
    double stopTime;
    bool newDiscreteStatesNeeded;
    bool terminateSimulation;
    bool nominalsOfContinuousStatesChanged;
    bool valuesOfContinuousStatesChanged;
    bool nextEventTimeDefined;
    double nextEventTime;
    ModelData data;
} Snapshot;

static void take_snapshot(const ModelInstance *m, Snapshot *s) {
    memset(s, 0, sizeof(*s));
    s->state = m->state;
    s->time = m->time;
    s->startTime = m->startTime;
    s->stopTimeDefined = m->stopTimeDefined;
    s->stopTime = m->stopTime;
    s->newDiscreteStatesNeeded = m->newDiscreteStatesNeeded;
    s->terminateSimulation = m->terminateSimulation;
    s->nominalsOfContinuousStatesChanged = m->nominalsOfContinuousStatesChanged;
    s->valuesOfContinuousStatesChanged = m->valuesOfContinuousStatesChanged;
    s->nextEventTimeDefined = m->nextEventTimeDefined;
    s->nextEventTime = m->nextEventTime;
    s->data = m->data;
}

static void restore_snapshot(ModelInstance *m, const Snapshot *s) {
    m->state = s->state;
    m->time = s->time;
    m->startTime = s->startTime;
    m->stopTimeDefined = s->stopTimeDefined;
    m->stopTime = s->stopTime;
    m->newDiscreteStatesNeeded = s->newDiscreteStatesNeeded;
    m->terminateSimulation = s->terminateSimulation;
    m->nominalsOfContinuousStatesChanged = s->nominalsOfContinuousStatesChanged;
    m->valuesOfContinuousStatesChanged = s->valuesOfContinuousStatesChanged;
    m->nextEventTimeDefined = s->nextEventTimeDefined;
    m->nextEventTime = s->nextEventTime;
    m->data = s->data;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, "fmi2GetFMUstate");
    if (m == NULL || !not_null(m, FMUstate, "FMUstate", "fmi2GetFMUstate")) {
        return fmi2Error;
    }
    /* A non-NULL *FMUstate is a snapshot from an earlier call: overwrite it in place. */
    Snapshot *s = (Snapshot *)*FMUstate;
    if (s == NULL) {
        s = allocate(m, sizeof(Snapshot));
        if (s == NULL) {
            model_log(m, fmi2Error, "logStatusError", "fmi2GetFMUstate: out of memory.");
            return fmi2Error;
        }
    }
    take_snapshot(m, s);
    *FMUstate = s;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, "fmi2SetFMUstate");
    if (m == NULL || !not_null(m, FMUstate, "FMUstate", "fmi2SetFMUstate")) {
        return fmi2Error;
    }
    restore_snapshot(m, (const Snapshot *)FMUstate);
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, "fmi2FreeFMUstate");
    if (m == NULL || !not_null(m, FMUstate, "FMUstate", "fmi2FreeFMUstate")) {
        return fmi2Error;
    }
    release(m, *FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

/* Serialized layout: a fixed header (magic, total size, GUID) followed by the Snapshot.
 * The GUID check rejects blobs written by another model; the size check rejects blobs
 * from a build with a different ModelData layout. */
#define SERIALIZATION_MAGIC "FMUBSER1"
#define GUID_FIELD_SIZE 64

typedef struct {
    char magic[8];
    uint64_t totalSize;
    char guid[GUID_FIELD_SIZE];
} SerializationHeader;

static const size_t SERIALIZED_SIZE = sizeof(SerializationHeader) + sizeof(Snapshot);

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, "fmi2SerializedFMUstateSize");
    if (m == NULL || !not_null(m, FMUstate, "FMUstate", "fmi2SerializedFMUstateSize") ||
        !not_null(m, size, "size", "fmi2SerializedFMUstateSize")) {
        return fmi2Error;
    }
    *size = SERIALIZED_SIZE;
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, "fmi2SerializeFMUstate");
    if (m == NULL || !not_null(m, FMUstate, "FMUstate", "fmi2SerializeFMUstate") ||
        !not_null(m, serializedState, "serializedState", "fmi2SerializeFMUstate")) {
        return fmi2Error;
    }
    if (size < SERIALIZED_SIZE) {
        model_log(m, fmi2Error, "logStatusError",
                  "fmi2SerializeFMUstate: buffer of %zu bytes is smaller than the %zu needed.",
                  size, SERIALIZED_SIZE);
        return fmi2Error;
    }
    SerializationHeader header;
    memset(&header, 0, sizeof(header));
    memcpy(header.magic, SERIALIZATION_MAGIC, sizeof(header.magic));
    header.totalSize = SERIALIZED_SIZE;
    strncpy(header.guid, MODEL_GUID, GUID_FIELD_SIZE - 1);
    memcpy(serializedState, &header, sizeof(header));
    memcpy(serializedState + sizeof(header), FMUstate, sizeof(Snapshot));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    ModelInstance *m = checked(c, MASK_FMU_STATE, "fmi2DeSerializeFMUstate");
    if (m == NULL || !not_null(m, serializedState, "serializedState", "fmi2DeSerializeFMUstate") ||
        !not_null(m, FMUstate, "FMUstate", "fmi2DeSerializeFMUstate")) {
        return fmi2Error;
    }
    SerializationHeader header;
    if (size != SERIALIZED_SIZE) {
        model_log(m, fmi2Error, "logStatusError",
                  "fmi2DeSerializeFMUstate: got %zu bytes, expected %zu for this model.", size,
                  SERIALIZED_SIZE);
        return fmi2Error;
    }
    memcpy(&header, serializedState, sizeof(header));
    if (memcmp(header.magic, SERIALIZATION_MAGIC, sizeof(header.magic)) != 0 ||
        header.totalSize != SERIALIZED_SIZE ||
        strncmp(header.guid, MODEL_GUID, GUID_FIELD_SIZE) != 0) {
        model_log(m, fmi2Error, "logStatusError",
                  "fmi2DeSerializeFMUstate: the data was not serialized by %s (GUID %s).",
                  MODEL_IDENTIFIER, MODEL_GUID);
        return fmi2Error;
    }
    Snapshot *s = allocate(m, sizeof(Snapshot));
    if (s == NULL) {
        model_log(m, fmi2Error, "logStatusError", "fmi2DeSerializeFMUstate: out of memory.");
        return fmi2Error;
    }
    memcpy(s, serializedState + sizeof(header), sizeof(Snapshot));
    *FMUstate = s;
    return fmi2OK;
}

#endif /* FMU_STATE_UNSUPPORTED */

/* ---------------------------------------------------------------------------------------
 * Directional derivatives: dvUnknown_i = sum_j d unknown_i / d known_j * dvKnown_j.
 */
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                        size_t nKnown, const fmi2Real dvKnown[],
                                        fmi2Real dvUnknown[]) {
    const char *fn = "fmi2GetDirectionalDerivative";
    ModelInstance *m = checked(c, MASK_GET_VALUES, fn);
    if (m == NULL) {
        return fmi2Error;
    }
#ifdef HAS_DIRECTIONAL_DERIVATIVE
    if (!array_ok(m, vUnknown_ref, nUnknown, "vUnknown_ref", fn) ||
        !array_ok(m, dvUnknown, nUnknown, "dvUnknown", fn) ||
        !array_ok(m, vKnown_ref, nKnown, "vKnown_ref", fn) ||
        !array_ok(m, dvKnown, nKnown, "dvKnown", fn)) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nUnknown; i++) {
        double sum = 0.0;
        for (size_t j = 0; j < nKnown; j++) {
            double partial = 0.0;
            if (model_get_partial_derivative(m, vUnknown_ref[i], vKnown_ref[j], &partial) !=
                fmi2OK) {
                model_log(m, fmi2Error, "logStatusError",
                          "%s: no partial derivative of vr=%u with respect to vr=%u.", fn,
                          vUnknown_ref[i], vKnown_ref[j]);
                return fmi2Error;
            }
            sum += partial * dvKnown[j];
        }
        dvUnknown[i] = sum;
    }
    return fmi2OK;
#else
    (void)vUnknown_ref;
    (void)nUnknown;
    (void)vKnown_ref;
    (void)nKnown;
    (void)dvKnown;
    (void)dvUnknown;
    model_log(m, fmi2Error, "logStatusError",
              "%s: %s does not provide directional derivatives.", fn, MODEL_IDENTIFIER);
    return fmi2Error;
#endif
}

/* ---------------------------------------------------------------------------------------
 * Model Exchange: event mode, continuous-time mode.
 */
fmi2Status fmi2EnterEventMode(fmi2Component c) {
    ModelInstance *m =
        checked(c, STATE_EVENT_MODE | STATE_CONTINUOUS_TIME_MODE, "fmi2EnterEventMode");
    if (m == NULL) {
        return fmi2Error;
    }
    m->state = STATE_EVENT_MODE;
    return fmi2OK;
}

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *eventInfo) {
    ModelInstance *m = checked(c, STATE_EVENT_MODE, "fmi2NewDiscreteStates");
    if (m == NULL || !not_null(m, eventInfo, "eventInfo", "fmi2NewDiscreteStates")) {
        return fmi2Error;
    }
    /* nextEventTime persists: the model changes it only when its schedule changes. */
    clear_event_flags(m);
    model_event_update(m);
    eventInfo->newDiscreteStatesNeeded = m->newDiscreteStatesNeeded;
    eventInfo->terminateSimulation = m->terminateSimulation;
    eventInfo->nominalsOfContinuousStatesChanged = m->nominalsOfContinuousStatesChanged;
    eventInfo->valuesOfContinuousStatesChanged = m->valuesOfContinuousStatesChanged;
    eventInfo->nextEventTimeDefined = m->nextEventTimeDefined;
    eventInfo->nextEventTime = m->nextEventTime;
    if (m->terminateSimulation) {
        model_log(m, fmi2OK, "logEvents", "Model requested termination at t=%g.", m->time);
    }
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    ModelInstance *m = checked(c, STATE_EVENT_MODE, "fmi2EnterContinuousTimeMode");
    if (m == NULL) {
        return fmi2Error;
    }
    m->state = STATE_CONTINUOUS_TIME_MODE;
    return fmi2OK;
}

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode,
                                       fmi2Boolean *terminateSimulation) {
    const char *fn = "fmi2CompletedIntegratorStep";
    ModelInstance *m = checked(c, STATE_CONTINUOUS_TIME_MODE, fn);
    (void)noSetFMUStatePriorToCurrentPoint;
    if (m == NULL || !not_null(m, enterEventMode, "enterEventMode", fn) ||
        !not_null(m, terminateSimulation, "terminateSimulation", fn)) {
        return fmi2Error;
    }
#ifdef HAS_STEP_EVENT
    *enterEventMode = model_completed_integrator_step(m) ? fmi2True : fmi2False;
#else
    *enterEventMode = fmi2False;
#endif
    *terminateSimulation = m->terminateSimulation ? fmi2True : fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    ModelInstance *m = checked(c, STATE_EVENT_MODE | STATE_CONTINUOUS_TIME_MODE, "fmi2SetTime");
    if (m == NULL) {
        return fmi2Error;
    }
    m->time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    const char *fn = "fmi2SetContinuousStates";
    ModelInstance *m = checked(c, STATE_CONTINUOUS_TIME_MODE, fn);
    if (m == NULL || !size_matches(m, nx, NX, "nx", fn) || !array_ok(m, x, nx, "x", fn)) {
        return fmi2Error;
    }
    if (nx > 0) {
        model_set_continuous_states(m, x);
    }
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    const char *fn = "fmi2GetDerivatives";
    ModelInstance *m = checked(c, MASK_GET_VALUES, fn);
    if (m == NULL || !size_matches(m, nx, NX, "nx", fn) ||
        !array_ok(m, derivatives, nx, "derivatives", fn)) {
        return fmi2Error;
    }
    if (nx > 0) {
        model_get_derivatives(m, derivatives);
    }
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    const char *fn = "fmi2GetEventIndicators";
    ModelInstance *m = checked(c, MASK_GET_VALUES, fn);
    if (m == NULL || !size_matches(m, ni, NZ, "ni", fn) ||
        !array_ok(m, eventIndicators, ni, "eventIndicators", fn)) {
        return fmi2Error;
    }
    if (ni > 0) {
        model_get_event_indicators(m, eventIndicators);
    }
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    const char *fn = "fmi2GetContinuousStates";
    ModelInstance *m = checked(c, MASK_GET_VALUES, fn);
    if (m == NULL || !size_matches(m, nx, NX, "nx", fn) || !array_ok(m, x, nx, "x", fn)) {
        return fmi2Error;
    }
    if (nx > 0) {
        model_get_continuous_states(m, x);
    }
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    const char *fn = "fmi2GetNominalsOfContinuousStates";
    ModelInstance *m = checked(c, MASK_NOMINALS, fn);
    if (m == NULL || !size_matches(m, nx, NX, "nx", fn) ||
        !array_ok(m, x_nominal, nx, "x_nominal", fn)) {
        return fmi2Error;
    }
    for (size_t i = 0; i < nx; i++) {
        x_nominal[i] = 1.0;
    }
    return fmi2OK;
}

/* ---------------------------------------------------------------------------------------
 * Co-Simulation is not supported: fmi2Instantiate refuses fmi2CoSimulation, so these are
 * only reachable with a Model Exchange instance and always fail with a message. With
 * WITHOUT_CO_SIMULATION_SYMBOLS they are left out, as a tool may leave them out of an FMU that
 * declares Model Exchange only (FMI 2.0.5, p. 69).
 */
#ifndef WITHOUT_CO_SIMULATION_SYMBOLS
static fmi2Status not_co_simulation(fmi2Component c, const char *function) {
    ModelInstance *m = (ModelInstance *)c;
    model_log(m, fmi2Error, "logStatusError", "%s: %s is a Model Exchange FMU only.", function,
              MODEL_IDENTIFIER);
    return fmi2Error;
}

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr, (void)nvr, (void)order, (void)value;
    return not_co_simulation(c, "fmi2SetRealInputDerivatives");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr, (void)nvr, (void)order, (void)value;
    return not_co_simulation(c, "fmi2GetRealOutputDerivatives");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)currentCommunicationPoint, (void)communicationStepSize;
    (void)noSetFMUStatePriorToCurrentPoint;
    return not_co_simulation(c, "fmi2DoStep");
}

fmi2Status fmi2CancelStep(fmi2Component c) { return not_co_simulation(c, "fmi2CancelStep"); }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s, (void)value;
    return not_co_simulation(c, "fmi2GetStatus");
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    (void)s, (void)value;
    return not_co_simulation(c, "fmi2GetRealStatus");
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s, (void)value;
    return not_co_simulation(c, "fmi2GetIntegerStatus");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)s, (void)value;
    return not_co_simulation(c, "fmi2GetBooleanStatus");
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s, (void)value;
    return not_co_simulation(c, "fmi2GetStringStatus");
}
#endif
