/*
 * Drives a hybrid FMU through the calls an importer must not make, and through many instances
 * at once, checking every answer:
 *
 *   fmu_attack LIBRARY GUID RESOURCE_URI N_STATES N_INDICATORS START_VR FIXED_VR GATE_VR
 *
 * START_VR is a Real parameter that sets where a run starts (settable before initialisation),
 * FIXED_VR a fixed parameter, GATE_VR a tunable gate of the hybrid. Checked:
 *   - a NULL instance, a wrong GUID, Co-Simulation, missing callbacks: fmi2Error or NULL, no crash;
 *   - calls in the wrong state (derivatives before initialisation, a fixed parameter after it,
 *     a gate in continuous-time mode, ...) return fmi2Error with a logged message naming the call;
 *   - NULL arrays and wrong array sizes: fmi2Error with a message;
 *   - an invalid value reference: fmi2Error, the instance is then in the Error state until
 *     fmi2Reset;
 *   - FMU states: foreign, freed and forged snapshots are refused; corrupt serialized bytes too;
 *   - freeing an instance twice;
 *   - 20 instances with different start values stepped in turn, and 2 threads with 10 instances
 *     each, end exactly where each run alone ends.
 * Prints "passed N checks" and exits 0, or names the failed check and exits 1. Meant to run
 * under AddressSanitizer/UndefinedBehaviorSanitizer, which add invalid accesses and leaks.
 */
#include <dlfcn.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

#define MAX_SIZE 64
#define N_INSTANCES 20
#define STEPS 300
#define STEP_SIZE 0.01

#define FMI_FUNCTIONS(X)                                                                           \
    X(fmi2Instantiate) X(fmi2FreeInstance) X(fmi2SetupExperiment) X(fmi2EnterInitializationMode)   \
    X(fmi2ExitInitializationMode) X(fmi2Terminate) X(fmi2Reset) X(fmi2GetReal) X(fmi2SetReal)       \
    X(fmi2GetInteger) X(fmi2SetInteger) X(fmi2EnterEventMode) X(fmi2NewDiscreteStates)             \
    X(fmi2EnterContinuousTimeMode) X(fmi2CompletedIntegratorStep) X(fmi2SetTime)                   \
    X(fmi2SetContinuousStates) X(fmi2GetDerivatives) X(fmi2GetEventIndicators)                     \
    X(fmi2GetContinuousStates) X(fmi2GetNominalsOfContinuousStates) X(fmi2GetFMUstate)             \
    X(fmi2SetFMUstate) X(fmi2FreeFMUstate) X(fmi2SerializedFMUstateSize) X(fmi2SerializeFMUstate)  \
    X(fmi2DeSerializeFMUstate) X(fmi2SetDebugLogging) X(fmi2DoStep)

#define FIELD(name) name##TYPE *name;
typedef struct {
    FMI_FUNCTIONS(FIELD)
} Api;

static Api api;
static const char *guid, *resources;
static size_t nx, nz;
static fmi2ValueReference start_vr, fixed_vr, gate_vr;
static int checks;

/* What an instance logged: the importer's environment, one per thread. */
typedef struct {
    int count;
    char last[1024];
} Log;

static void logger(fmi2ComponentEnvironment env, fmi2String name, fmi2Status status, fmi2String category,
                   fmi2String message, ...) {
    Log *log = (Log *)env;
    va_list args;
    (void)name, (void)status, (void)category;
    va_start(args, message);
    vsnprintf(log->last, sizeof(log->last), message, args);
    va_end(args);
    log->count++;
}

static void fail(int line, const char *what, const Log *log) {
    fprintf(stderr, "check at line %d failed: %s (last message: %s)\n", line, what, log ? log->last : "-");
    exit(1);
}

#define EXPECT(condition, log)                                                                     \
    do {                                                                                           \
        __atomic_fetch_add(&checks, 1, __ATOMIC_RELAXED);                                          \
        if (!(condition)) fail(__LINE__, #condition, log);                                          \
    } while (0)

#define OK(call, log) EXPECT((call) <= fmi2Warning, log)

/* `call` returns fmi2Error and logs a new message that contains `text`. */
#define REFUSED(call, log, text)                                                                   \
    do {                                                                                           \
        int before = (log)->count;                                                                 \
        EXPECT((call) == fmi2Error, log);                                                          \
        EXPECT((log)->count > before && strstr((log)->last, text) != NULL, log);                   \
    } while (0)

static fmi2CallbackFunctions callbacks_for(Log *log) {
    fmi2CallbackFunctions callbacks = {logger, calloc, free, NULL, log};
    return callbacks;
}

static fmi2Component instantiate(const fmi2CallbackFunctions *callbacks, Log *log) {
    fmi2Component c = api.fmi2Instantiate("attack", fmi2ModelExchange, guid, resources, callbacks, fmi2False,
                                          fmi2False);
    EXPECT(c != NULL, log);
    return c;
}

static void event_iteration(fmi2Component c, Log *log) {
    fmi2EventInfo info;
    do {
        info.newDiscreteStatesNeeded = fmi2False;
        OK(api.fmi2NewDiscreteStates(c, &info), log);
    } while (info.newDiscreteStatesNeeded && !info.terminateSimulation);
}

static void start(fmi2Component c, Log *log) {
    OK(api.fmi2SetupExperiment(c, fmi2False, 0.0, 0.0, fmi2False, 0.0), log);
    OK(api.fmi2EnterInitializationMode(c), log);
    OK(api.fmi2ExitInitializationMode(c), log);
    event_iteration(c, log);
    OK(api.fmi2EnterContinuousTimeMode(c), log);
}

/* One forward-Euler step with event handling at its end. */
static void step(fmi2Component c, int n, Log *log) {
    double x[MAX_SIZE], dx[MAX_SIZE], z[MAX_SIZE], z_after[MAX_SIZE];
    fmi2Boolean enter_event = fmi2False, terminate = fmi2False;
    int state_event = 0;
    OK(api.fmi2GetEventIndicators(c, z, nz), log);
    OK(api.fmi2GetContinuousStates(c, x, nx), log);
    OK(api.fmi2GetDerivatives(c, dx, nx), log);
    for (size_t i = 0; i < nx; i++) {
        x[i] += STEP_SIZE * dx[i];
    }
    OK(api.fmi2SetTime(c, (n + 1) * STEP_SIZE), log);
    OK(api.fmi2SetContinuousStates(c, x, nx), log);
    OK(api.fmi2GetEventIndicators(c, z_after, nz), log);
    for (size_t i = 0; i < nz; i++) {
        state_event |= (z[i] < 0) != (z_after[i] < 0);
    }
    OK(api.fmi2CompletedIntegratorStep(c, fmi2True, &enter_event, &terminate), log);
    if (state_event || enter_event) {
        OK(api.fmi2EnterEventMode(c), log);
        event_iteration(c, log);
        OK(api.fmi2EnterContinuousTimeMode(c), log);
    }
}

static void finish(fmi2Component c, double *x, Log *log) {
    OK(api.fmi2GetContinuousStates(c, x, nx), log);
    OK(api.fmi2Terminate(c), log);
    api.fmi2FreeInstance(c);
}

/* `count` instances with start values start_of(first..), stepped in turn; final states in x. */
static double start_value(int k) { return 0.5 + 0.25 * k; }

static void run_interleaved(int first, int count, double x[][MAX_SIZE], Log *log) {
    fmi2CallbackFunctions callbacks = callbacks_for(log);
    fmi2Component c[N_INSTANCES];
    for (int k = 0; k < count; k++) {
        double value = start_value(first + k);
        c[k] = instantiate(&callbacks, log);
        OK(api.fmi2SetReal(c[k], &start_vr, 1, &value), log);
        start(c[k], log);
    }
    for (int n = 0; n < STEPS; n++) {
        for (int k = 0; k < count; k++) {
            step(c[k], n, log);
        }
    }
    for (int k = 0; k < count; k++) {
        finish(c[k], x[first + k], log);
    }
}

typedef struct {
    int first, count;
    double (*x)[MAX_SIZE];
    Log log;
} Job;

static void *run_job(void *argument) {
    Job *job = (Job *)argument;
    run_interleaved(job->first, job->count, job->x, &job->log);
    return NULL;
}

static void many_instances(void) {
    static double alone[N_INSTANCES][MAX_SIZE], together[N_INSTANCES][MAX_SIZE], threaded[N_INSTANCES][MAX_SIZE];
    Log log = {0, ""};
    Job jobs[2] = {{0, N_INSTANCES / 2, threaded, {0, ""}}, {N_INSTANCES / 2, N_INSTANCES / 2, threaded, {0, ""}}};
    pthread_t threads[2];
    for (int k = 0; k < N_INSTANCES; k++) {
        run_interleaved(k, 1, alone, &log);
    }
    run_interleaved(0, N_INSTANCES, together, &log);
    for (int t = 0; t < 2; t++) {
        EXPECT(pthread_create(&threads[t], NULL, run_job, &jobs[t]) == 0, &log);
    }
    for (int t = 0; t < 2; t++) {
        EXPECT(pthread_join(threads[t], NULL) == 0, &log);
    }
    for (int k = 0; k < N_INSTANCES; k++) {
        EXPECT(memcmp(alone[k], together[k], nx * sizeof(double)) == 0, &log);
        EXPECT(memcmp(alone[k], threaded[k], nx * sizeof(double)) == 0, &log);
    }
    /* The start values matter: different instances really ran different models. */
    EXPECT(memcmp(alone[0], alone[N_INSTANCES - 1], nx * sizeof(double)) != 0, &log);
}

static void null_instance_and_bad_instantiation(void) {
    Log log = {0, ""};
    fmi2CallbackFunctions callbacks = callbacks_for(&log);
    fmi2CallbackFunctions no_memory = {logger, NULL, NULL, NULL, &log};
    double values[MAX_SIZE + 1];
    fmi2FMUstate state = NULL;
    EXPECT(api.fmi2GetReal(NULL, &start_vr, 1, values) == fmi2Error, &log);
    EXPECT(api.fmi2SetReal(NULL, &start_vr, 1, values) == fmi2Error, &log);
    EXPECT(api.fmi2GetDerivatives(NULL, values, nx) == fmi2Error, &log);
    EXPECT(api.fmi2EnterInitializationMode(NULL) == fmi2Error, &log);
    EXPECT(api.fmi2GetFMUstate(NULL, &state) == fmi2Error, &log);
    EXPECT(api.fmi2Reset(NULL) == fmi2Error, &log);
    EXPECT(api.fmi2DoStep(NULL, 0.0, 0.1, fmi2True) == fmi2Error, &log);
    api.fmi2FreeInstance(NULL);
    EXPECT(api.fmi2Instantiate("x", fmi2ModelExchange, guid, resources, NULL, 0, 0) == NULL, &log);
    EXPECT(api.fmi2Instantiate("x", fmi2ModelExchange, guid, resources, &no_memory, 0, 0) == NULL, &log);
    EXPECT(api.fmi2Instantiate("x", fmi2ModelExchange, "{wrong}", resources, &callbacks, 0, 0) == NULL, &log);
    EXPECT(strstr(log.last, "does not match") != NULL, &log);
    EXPECT(api.fmi2Instantiate("x", fmi2CoSimulation, guid, resources, &callbacks, 0, 0) == NULL, &log);
    EXPECT(strstr(log.last, "Model Exchange only") != NULL, &log);
    EXPECT(api.fmi2Instantiate(NULL, fmi2ModelExchange, guid, "file:///no/such/folder", &callbacks, 0, 0) == NULL,
           &log);
    EXPECT(strstr(log.last, "cannot load") != NULL, &log);
}

static void wrong_states(void) {
    Log log = {0, ""};
    fmi2CallbackFunctions callbacks = callbacks_for(&log);
    fmi2Component c = instantiate(&callbacks, &log);
    double values[MAX_SIZE + 1], one = 1.0;
    fmi2Boolean flag;
    fmi2EventInfo info;
    REFUSED(api.fmi2GetDerivatives(c, values, nx), &log, "fmi2GetDerivatives must not be called in state Instantiated");
    REFUSED(api.fmi2GetContinuousStates(c, values, nx), &log, "fmi2GetContinuousStates must not be called");
    REFUSED(api.fmi2GetReal(c, &gate_vr, 1, values), &log, "fmi2GetReal must not be called");
    REFUSED(api.fmi2EnterContinuousTimeMode(c), &log, "fmi2EnterContinuousTimeMode must not be called");
    REFUSED(api.fmi2ExitInitializationMode(c), &log, "fmi2ExitInitializationMode must not be called");
    REFUSED(api.fmi2NewDiscreteStates(c, &info), &log, "fmi2NewDiscreteStates must not be called");
    REFUSED(api.fmi2CompletedIntegratorStep(c, fmi2True, &flag, &flag), &log, "must not be called");
    REFUSED(api.fmi2SetTime(c, 1.0), &log, "fmi2SetTime must not be called");
    REFUSED(api.fmi2Terminate(c), &log, "fmi2Terminate must not be called");
    REFUSED(api.fmi2DoStep(c, 0.0, 0.1, fmi2True), &log, "Model Exchange only");
    start(c, &log);
    REFUSED(api.fmi2SetupExperiment(c, fmi2False, 0.0, 0.0, fmi2False, 0.0), &log, "must not be called");
    REFUSED(api.fmi2EnterInitializationMode(c), &log, "must not be called");
    REFUSED(api.fmi2NewDiscreteStates(c, &info), &log, "must not be called in state ContinuousTimeMode");
    REFUSED(api.fmi2SetReal(c, &gate_vr, 1, &one), &log, "can be set before initialization or in event mode");
    /* The wrapper's own refusals leave the instance usable. */
    OK(api.fmi2GetDerivatives(c, values, nx), &log);
    /* A fixed parameter after initialisation: the original refuses, the instance is in Error. */
    REFUSED(api.fmi2SetReal(c, &fixed_vr, 1, &one), &log, "Error state");
    REFUSED(api.fmi2SetContinuousStates(c, values, nx), &log, "must not be called in state Error");
    REFUSED(api.fmi2EnterEventMode(c), &log, "must not be called in state Error");
    OK(api.fmi2GetDerivatives(c, values, nx), &log); /* values may still be read */
    OK(api.fmi2Reset(c), &log);
    start(c, &log);
    OK(api.fmi2Terminate(c), &log);
    REFUSED(api.fmi2SetTime(c, 1.0), &log, "must not be called in state Terminated");
    REFUSED(api.fmi2EnterEventMode(c), &log, "must not be called in state Terminated");
    api.fmi2FreeInstance(c);
    api.fmi2FreeInstance(c); /* twice: ignored */
}

static void bad_arguments(void) {
    Log log = {0, ""};
    fmi2CallbackFunctions callbacks = callbacks_for(&log);
    fmi2Component c = instantiate(&callbacks, &log);
    double values[MAX_SIZE + 1];
    fmi2ValueReference invalid = 999999;
    start(c, &log);
    REFUSED(api.fmi2GetDerivatives(c, values, nx + 1), &log, "size argument");
    REFUSED(api.fmi2GetDerivatives(c, NULL, nx), &log, "must not be NULL");
    REFUSED(api.fmi2GetContinuousStates(c, values, nx + 1), &log, "size argument");
    REFUSED(api.fmi2SetContinuousStates(c, values, nx + 1), &log, "size argument");
    REFUSED(api.fmi2GetNominalsOfContinuousStates(c, values, nx + 1), &log, "size argument");
    REFUSED(api.fmi2GetEventIndicators(c, values, nz + 1), &log, "size argument");
    REFUSED(api.fmi2GetReal(c, NULL, 1, values), &log, "must not be NULL");
    REFUSED(api.fmi2GetReal(c, &gate_vr, 1, NULL), &log, "must not be NULL");
    REFUSED(api.fmi2SetDebugLogging(c, fmi2True, 1, NULL), &log, "must not be NULL");
    {
        fmi2String unknown = "noSuchCategory";
        REFUSED(api.fmi2SetDebugLogging(c, fmi2True, 1, &unknown), &log, "unknown log category");
    }
    OK(api.fmi2GetDerivatives(c, values, nx), &log);
    /* An invalid value reference: the original refuses it, the instance enters the Error state. */
    REFUSED(api.fmi2GetReal(c, &invalid, 1, values), &log, "Error state");
    REFUSED(api.fmi2SetTime(c, 0.5), &log, "must not be called in state Error");
    OK(api.fmi2Reset(c), &log);
    start(c, &log);
    REFUSED(api.fmi2GetInteger(c, &invalid, 1, (fmi2Integer *)values), &log, "Error state");
    api.fmi2FreeInstance(c);
}

static void fmu_states(void) {
    Log log = {0, ""};
    fmi2CallbackFunctions callbacks = callbacks_for(&log);
    fmi2Component a = instantiate(&callbacks, &log), b = instantiate(&callbacks, &log);
    fmi2FMUstate state = NULL, copy = NULL, forged;
    double zeros[64] = {0};
    size_t size = 0;
    fmi2Byte *bytes;
    start(a, &log);
    start(b, &log);
    OK(api.fmi2GetFMUstate(a, &state), &log);
    REFUSED(api.fmi2SetFMUstate(b, state), &log, "not made by this instance");
    REFUSED(api.fmi2FreeFMUstate(b, &state), &log, "not made by this instance");
    forged = (fmi2FMUstate)zeros;
    REFUSED(api.fmi2SetFMUstate(a, forged), &log, "not made by this instance");
    REFUSED(api.fmi2SetFMUstate(a, NULL), &log, "must not be NULL");
    OK(api.fmi2SerializedFMUstateSize(a, state, &size), &log);
    bytes = malloc(size);
    OK(api.fmi2SerializeFMUstate(a, state, bytes, size), &log);
    REFUSED(api.fmi2SerializeFMUstate(a, state, bytes, 4), &log, "too small");
    /* Corrupt bytes are refused before the original sees them, and the instance stays usable. */
    REFUSED(api.fmi2DeSerializeFMUstate(a, bytes, 10, &copy), &log, "not a serialized state");
    bytes[0] ^= 1;
    REFUSED(api.fmi2DeSerializeFMUstate(a, bytes, size, &copy), &log, "not a serialized state");
    bytes[0] ^= 1;
    bytes[8] = 99; /* the instance state: not one state bit */
    REFUSED(api.fmi2DeSerializeFMUstate(a, bytes, size, &copy), &log, "invalid instance state");
    OK(api.fmi2SerializeFMUstate(a, state, bytes, size), &log);
    bytes[12] = 7; /* the number of channels */
    REFUSED(api.fmi2DeSerializeFMUstate(a, bytes, size, &copy), &log, "channels");
    OK(api.fmi2SerializeFMUstate(a, state, bytes, size), &log);
    {
        double nan = NAN;
        memcpy(bytes + 16, &nan, sizeof(nan)); /* the first gate */
    }
    REFUSED(api.fmi2DeSerializeFMUstate(a, bytes, size, &copy), &log, "not finite");
    EXPECT(copy == NULL, &log);
    OK(api.fmi2SerializeFMUstate(a, state, bytes, size), &log);
    OK(api.fmi2DeSerializeFMUstate(a, bytes, size, &copy), &log);
    OK(api.fmi2SetFMUstate(a, copy), &log);
    OK(api.fmi2FreeFMUstate(a, &copy), &log);
    EXPECT(copy == NULL, &log);
    OK(api.fmi2FreeFMUstate(a, &copy), &log); /* freeing NULL again: nothing to do */
    OK(api.fmi2FreeFMUstate(a, &state), &log);
    free(bytes);
    api.fmi2FreeInstance(a);
    api.fmi2FreeInstance(b);
}

#define LOOK_UP(name)                                                                              \
    api.name = (name##TYPE *)dlsym(library, #name);                                                \
    if (api.name == NULL) {                                                                        \
        fprintf(stderr, "missing symbol %s\n", #name);                                             \
        return 2;                                                                                  \
    }

int main(int argc, char **argv) {
    void *library;
    if (argc != 9) {
        fprintf(stderr, "usage: %s LIBRARY GUID RESOURCE_URI N_STATES N_INDICATORS START_VR FIXED_VR GATE_VR\n",
                argv[0]);
        return 2;
    }
    guid = argv[2];
    resources = argv[3];
    nx = (size_t)atoi(argv[4]);
    nz = (size_t)atoi(argv[5]);
    start_vr = (fmi2ValueReference)strtoul(argv[6], NULL, 10);
    fixed_vr = (fmi2ValueReference)strtoul(argv[7], NULL, 10);
    gate_vr = (fmi2ValueReference)strtoul(argv[8], NULL, 10);
    if (nx > MAX_SIZE || nz > MAX_SIZE) {
        fprintf(stderr, "too many states or indicators\n");
        return 2;
    }
    library = dlopen(argv[1], RTLD_NOW | (getenv("FMU_HOST_RTLD_LOCAL") ? RTLD_LOCAL : RTLD_GLOBAL));
    if (library == NULL) {
        fprintf(stderr, "dlopen failed: %s\n", dlerror());
        return 2;
    }
    FMI_FUNCTIONS(LOOK_UP)
    null_instance_and_bad_instantiation();
    wrong_states();
    bad_arguments();
    fmu_states();
    many_instances();
    dlclose(library);
    printf("passed %d checks\n", checks);
    return 0;
}
