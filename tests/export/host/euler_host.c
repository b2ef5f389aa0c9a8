/*
 * Portable FMI 2.0 Model-Exchange host: the same source compiled for Linux and, with mingw-w64,
 * for Windows, to compare a hybrid FMU's two binaries.
 *
 *   euler_host [--rewind] FMU_DIR IDENTIFIER GUID N_STATES N_INDICATORS STOP_TIME STEP_SIZE [VR...]
 *
 * FMU_DIR is the unpacked FMU (under wine, a Windows path such as Z:/tmp/x). Loads
 * FMU_DIR/binaries/<linux64|win64>/IDENTIFIER.<so|dll>, instantiates it with FMU_DIR/resources
 * as the resource location, initialises, and integrates with fixed-step explicit Euler:
 * t_k = k * STEP_SIZE; a state event when an event indicator changes sign over a step, a time
 * event when t_k reaches the FMU's next event time, both handled at the step's end. Prints one
 * line per step (the start included): t, the states, the Real values of the VRs, each with 17
 * significant digits. With --rewind the FMU state at the middle step is taken, serialized and
 * deserialized; after the last step it is set and the second half is integrated and printed
 * again. Exit code 0 when every call succeeded.
 */
#ifdef _WIN32
#define WIN32_LEAN_AND_MEAN
#define __USE_MINGW_ANSI_STDIO 1 /* C99 printf: %.17g exact on every C runtime */
#include <windows.h>
#else
#include <dlfcn.h>
#endif
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

#define MAX_SIZE 64
#define PATH_SIZE 4096

#ifdef _WIN32
#define PLATFORM "win64"
#define SUFFIX ".dll"
static void *open_library(const char *path) { return (void *)LoadLibraryA(path); }
static void (*symbol(void *library, const char *name))(void) {
    return (void (*)(void))GetProcAddress((HMODULE)library, name);
}
#else
#define PLATFORM "linux64"
#define SUFFIX ".so"
static void *open_library(const char *path) { return dlopen(path, RTLD_NOW | RTLD_LOCAL); }
static void (*symbol(void *library, const char *name))(void) {
    void (*function)(void);
    *(void **)&function = dlsym(library, name);
    return function;
}
#endif

typedef struct {
    fmi2InstantiateTYPE *instantiate;
    fmi2FreeInstanceTYPE *freeInstance;
    fmi2SetupExperimentTYPE *setupExperiment;
    fmi2EnterInitializationModeTYPE *enterInitializationMode;
    fmi2ExitInitializationModeTYPE *exitInitializationMode;
    fmi2NewDiscreteStatesTYPE *newDiscreteStates;
    fmi2EnterContinuousTimeModeTYPE *enterContinuousTimeMode;
    fmi2EnterEventModeTYPE *enterEventMode;
    fmi2GetContinuousStatesTYPE *getContinuousStates;
    fmi2SetContinuousStatesTYPE *setContinuousStates;
    fmi2GetDerivativesTYPE *getDerivatives;
    fmi2GetEventIndicatorsTYPE *getEventIndicators;
    fmi2SetTimeTYPE *setTime;
    fmi2CompletedIntegratorStepTYPE *completedIntegratorStep;
    fmi2GetRealTYPE *getReal;
    fmi2GetFMUstateTYPE *getFMUstate;
    fmi2SetFMUstateTYPE *setFMUstate;
    fmi2FreeFMUstateTYPE *freeFMUstate;
    fmi2SerializedFMUstateSizeTYPE *serializedFMUstateSize;
    fmi2SerializeFMUstateTYPE *serializeFMUstate;
    fmi2DeSerializeFMUstateTYPE *deSerializeFMUstate;
    fmi2TerminateTYPE *terminate;
} Api;

/* What the integration carries from step to step (the FMU holds the rest). */
typedef struct {
    size_t nx, nz, nvr;
    double h;
    double x[MAX_SIZE], z_before[MAX_SIZE];
    fmi2EventInfo info;
    const fmi2ValueReference *vrs;
} Run;

static void logger(fmi2ComponentEnvironment env, fmi2String name, fmi2Status status, fmi2String category,
                   fmi2String message, ...) {
    va_list args;
    (void)env;
    fprintf(stderr, "[%s|%d|%s] ", name ? name : "", (int)status, category ? category : "");
    va_start(args, message);
    vfprintf(stderr, message, args);
    va_end(args);
    fputc('\n', stderr);
}

static int fail(const char *what) {
    fprintf(stderr, "euler_host: %s\n", what);
    return 1;
}

#define CHECK(call)                          \
    do {                                     \
        if ((call) > fmi2Warning) {          \
            return fail(#call " failed");    \
        }                                    \
    } while (0)

#define LOAD(field, name)                                           \
    do {                                                            \
        api->field = (name##TYPE *)symbol(library, #name);          \
        if (api->field == NULL) {                                   \
            fprintf(stderr, "euler_host: no %s\n", #name);          \
            return 0;                                               \
        }                                                           \
    } while (0)

static int load_api(void *library, Api *api) {
    LOAD(instantiate, fmi2Instantiate);
    LOAD(freeInstance, fmi2FreeInstance);
    LOAD(setupExperiment, fmi2SetupExperiment);
    LOAD(enterInitializationMode, fmi2EnterInitializationMode);
    LOAD(exitInitializationMode, fmi2ExitInitializationMode);
    LOAD(newDiscreteStates, fmi2NewDiscreteStates);
    LOAD(enterContinuousTimeMode, fmi2EnterContinuousTimeMode);
    LOAD(enterEventMode, fmi2EnterEventMode);
    LOAD(getContinuousStates, fmi2GetContinuousStates);
    LOAD(setContinuousStates, fmi2SetContinuousStates);
    LOAD(getDerivatives, fmi2GetDerivatives);
    LOAD(getEventIndicators, fmi2GetEventIndicators);
    LOAD(setTime, fmi2SetTime);
    LOAD(completedIntegratorStep, fmi2CompletedIntegratorStep);
    LOAD(getReal, fmi2GetReal);
    LOAD(getFMUstate, fmi2GetFMUstate);
    LOAD(setFMUstate, fmi2SetFMUstate);
    LOAD(freeFMUstate, fmi2FreeFMUstate);
    LOAD(serializedFMUstateSize, fmi2SerializedFMUstateSize);
    LOAD(serializeFMUstate, fmi2SerializeFMUstate);
    LOAD(deSerializeFMUstate, fmi2DeSerializeFMUstate);
    LOAD(terminate, fmi2Terminate);
    return 1;
}

/* Event iteration until the FMU asks for no more; keeps the next time event in `info`. */
static int iterate_events(const Api *api, fmi2Component c, fmi2EventInfo *info) {
    info->newDiscreteStatesNeeded = fmi2True;
    while (info->newDiscreteStatesNeeded && !info->terminateSimulation) {
        CHECK(api->newDiscreteStates(c, info));
    }
    return 0;
}

static void print_row(const Api *api, fmi2Component c, double t, const double *x, size_t nx,
                      const fmi2ValueReference *vrs, size_t nvr) {
    double values[MAX_SIZE];
    printf("%.17g", t);
    for (size_t i = 0; i < nx; i++) {
        printf(" %.17g", x[i]);
    }
    if (nvr > 0 && api->getReal(c, vrs, nvr, values) <= fmi2Warning) {
        for (size_t i = 0; i < nvr; i++) {
            printf(" %.17g", values[i]);
        }
    }
    printf("\n");
}

/* Steps first..last (t_k = k h), each printed. */
static int integrate(const Api *api, fmi2Component c, Run *r, long first, long last) {
    double dx[MAX_SIZE], z[MAX_SIZE];
    fmi2Boolean enter_event_mode, terminate;
    for (long k = first; k <= last && !r->info.terminateSimulation; k++) {
        double t = (double)k * r->h;
        int state_event = 0, time_event;
        CHECK(api->getDerivatives(c, dx, r->nx));
        for (size_t i = 0; i < r->nx; i++) {
            r->x[i] += r->h * dx[i];
        }
        CHECK(api->setTime(c, t));
        CHECK(api->setContinuousStates(c, r->x, r->nx));
        CHECK(api->getEventIndicators(c, z, r->nz));
        for (size_t i = 0; i < r->nz; i++) {
            state_event |= (r->z_before[i] > 0.0) != (z[i] > 0.0);
        }
        time_event = r->info.nextEventTimeDefined && t >= r->info.nextEventTime;
        CHECK(api->completedIntegratorStep(c, fmi2True, &enter_event_mode, &terminate));
        if (terminate) break;
        if (state_event || time_event || enter_event_mode) {
            CHECK(api->enterEventMode(c));
            if (iterate_events(api, c, &r->info) != 0) return 1;
            CHECK(api->enterContinuousTimeMode(c));
            CHECK(api->getContinuousStates(c, r->x, r->nx));
            CHECK(api->getEventIndicators(c, z, r->nz));
        }
        memcpy(r->z_before, z, r->nz * sizeof(double));
        print_row(api, c, t, r->x, r->nx, r->vrs, r->nvr);
    }
    return 0;
}

/* The FMU state through its serialized form: get, serialize, deserialize. */
static int snapshot(const Api *api, fmi2Component c, fmi2FMUstate *restored) {
    fmi2FMUstate taken = NULL;
    size_t size = 0;
    char *bytes;
    CHECK(api->getFMUstate(c, &taken));
    CHECK(api->serializedFMUstateSize(c, taken, &size));
    bytes = malloc(size > 0 ? size : 1);
    if (bytes == NULL) return fail("out of memory");
    CHECK(api->serializeFMUstate(c, taken, (fmi2Byte *)bytes, size));
    CHECK(api->freeFMUstate(c, &taken));
    *restored = NULL;
    CHECK(api->deSerializeFMUstate(c, (const fmi2Byte *)bytes, size, restored));
    free(bytes);
    return 0;
}

static int simulate(const Api *api, fmi2Component c, Run *r, double stop, int rewind) {
    long steps = (long)floor(stop / r->h + 0.5), middle = steps / 2;
    fmi2FMUstate state = NULL;
    fmi2EventInfo info_at_middle;

    CHECK(api->setupExperiment(c, fmi2False, 0.0, 0.0, fmi2True, stop));
    CHECK(api->enterInitializationMode(c));
    CHECK(api->exitInitializationMode(c));
    if (iterate_events(api, c, &r->info) != 0) return 1;
    CHECK(api->enterContinuousTimeMode(c));
    CHECK(api->getContinuousStates(c, r->x, r->nx));
    CHECK(api->getEventIndicators(c, r->z_before, r->nz));
    print_row(api, c, 0.0, r->x, r->nx, r->vrs, r->nvr);

    if (!rewind) {
        if (integrate(api, c, r, 1, steps) != 0) return 1;
    } else {
        if (integrate(api, c, r, 1, middle) != 0 || snapshot(api, c, &state) != 0) return 1;
        info_at_middle = r->info;
        if (integrate(api, c, r, middle + 1, steps) != 0) return 1;
        /* Back to the middle: the FMU from its state, the host's own variables as they were. */
        CHECK(api->setFMUstate(c, state));
        CHECK(api->freeFMUstate(c, &state));
        r->info = info_at_middle;
        CHECK(api->getContinuousStates(c, r->x, r->nx));
        CHECK(api->getEventIndicators(c, r->z_before, r->nz));
        if (integrate(api, c, r, middle + 1, steps) != 0) return 1;
    }
    CHECK(api->terminate(c));
    return 0;
}

/* file:///FMU_DIR/resources, with the folder's separators as '/'. */
static void resource_uri(const char *fmu_dir, char *uri, size_t size) {
    const char *slash = fmu_dir[0] == '/' ? "" : "/";
    snprintf(uri, size, "file://%s%s/resources", slash, fmu_dir);
    for (char *p = uri; *p != '\0'; p++) {
        if (*p == '\\') *p = '/';
    }
}

int main(int argc, char **argv) {
    fmi2CallbackFunctions callbacks = {logger, calloc, free, NULL, NULL};
    fmi2ValueReference vrs[MAX_SIZE];
    char library_path[PATH_SIZE], uri[PATH_SIZE];
    void *library;
    Api api;
    Run run;
    fmi2Component c;
    int result, rewind = argc > 1 && strcmp(argv[1], "--rewind") == 0;

    argc -= rewind;
    argv += rewind;
    if (argc < 8) {
        return fail("usage: euler_host [--rewind] FMU_DIR IDENTIFIER GUID N_STATES N_INDICATORS STOP_TIME STEP_SIZE [VR...]");
    }
    memset(&run, 0, sizeof(run));
    run.nx = (size_t)atoi(argv[4]);
    run.nz = (size_t)atoi(argv[5]);
    run.h = atof(argv[7]);
    run.nvr = (size_t)(argc - 8);
    run.vrs = vrs;
    if (run.nx > MAX_SIZE || run.nz > MAX_SIZE || run.nvr > MAX_SIZE) {
        return fail("too many states, event indicators or value references");
    }
    for (size_t i = 0; i < run.nvr; i++) {
        vrs[i] = (fmi2ValueReference)strtoul(argv[8 + i], NULL, 10);
    }
    snprintf(library_path, sizeof(library_path), "%s/binaries/%s/%s%s", argv[1], PLATFORM, argv[2], SUFFIX);
    resource_uri(argv[1], uri, sizeof(uri));
    library = open_library(library_path);
    if (library == NULL) {
        fprintf(stderr, "euler_host: cannot load %s\n", library_path);
        return 1;
    }
    if (!load_api(library, &api)) {
        return 1;
    }
    c = api.instantiate("host", fmi2ModelExchange, argv[3], uri, &callbacks, fmi2False, fmi2False);
    if (c == NULL) {
        return fail("fmi2Instantiate failed");
    }
    result = simulate(&api, c, &run, atof(argv[6]), rewind);
    api.freeInstance(c);
    return result;
}
