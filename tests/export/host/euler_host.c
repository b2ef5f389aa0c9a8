/*
 * Portable FMI 2.0 Model-Exchange host: the same source compiled for Linux and, with mingw-w64,
 * for Windows, to compare a hybrid FMU's two binaries.
 *
 *   euler_host FMU_DIR IDENTIFIER GUID N_STATES N_INDICATORS STOP_TIME STEP_SIZE [VR...]
 *
 * FMU_DIR is the unpacked FMU (under wine, a Windows path such as Z:/tmp/x). Loads
 * FMU_DIR/binaries/<linux64|win64>/IDENTIFIER.<so|dll>, instantiates it with FMU_DIR/resources
 * as the resource location, initialises, and integrates with fixed-step explicit Euler:
 * t_k = k * STEP_SIZE; a state event when an event indicator changes sign over a step, a time
 * event when t_k reaches the FMU's next event time, both handled at the step's end. Prints one
 * line per step (the start included): t, the states, the Real values of the VRs, each with 17
 * significant digits. Exit code 0 when every call succeeded.
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
    fmi2TerminateTYPE *terminate;
} Api;

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

static int simulate(const Api *api, fmi2Component c, size_t nx, size_t nz, double stop, double h,
                    const fmi2ValueReference *vrs, size_t nvr) {
    double x[MAX_SIZE], dx[MAX_SIZE], z[MAX_SIZE], z_before[MAX_SIZE];
    fmi2EventInfo info;
    fmi2Boolean enter_event_mode, terminate;
    long steps = (long)floor(stop / h + 0.5);

    CHECK(api->setupExperiment(c, fmi2False, 0.0, 0.0, fmi2True, stop));
    CHECK(api->enterInitializationMode(c));
    CHECK(api->exitInitializationMode(c));
    if (iterate_events(api, c, &info) != 0) return 1;
    CHECK(api->enterContinuousTimeMode(c));
    CHECK(api->getContinuousStates(c, x, nx));
    CHECK(api->getEventIndicators(c, z_before, nz));
    print_row(api, c, 0.0, x, nx, vrs, nvr);

    for (long k = 1; k <= steps && !info.terminateSimulation; k++) {
        double t = (double)k * h;
        int state_event = 0, time_event;
        CHECK(api->getDerivatives(c, dx, nx));
        for (size_t i = 0; i < nx; i++) {
            x[i] += h * dx[i];
        }
        CHECK(api->setTime(c, t));
        CHECK(api->setContinuousStates(c, x, nx));
        CHECK(api->getEventIndicators(c, z, nz));
        for (size_t i = 0; i < nz; i++) {
            state_event |= (z_before[i] > 0.0) != (z[i] > 0.0);
        }
        time_event = info.nextEventTimeDefined && t >= info.nextEventTime;
        CHECK(api->completedIntegratorStep(c, fmi2True, &enter_event_mode, &terminate));
        if (terminate) break;
        if (state_event || time_event || enter_event_mode) {
            CHECK(api->enterEventMode(c));
            if (iterate_events(api, c, &info) != 0) return 1;
            CHECK(api->enterContinuousTimeMode(c));
            CHECK(api->getContinuousStates(c, x, nx));
            CHECK(api->getEventIndicators(c, z, nz));
        }
        memcpy(z_before, z, nz * sizeof(double));
        print_row(api, c, t, x, nx, vrs, nvr);
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
    size_t nx, nz, nvr;
    void *library;
    Api api;
    fmi2Component c;
    int result;

    if (argc < 8) {
        return fail("usage: euler_host FMU_DIR IDENTIFIER GUID N_STATES N_INDICATORS STOP_TIME STEP_SIZE [VR...]");
    }
    nx = (size_t)atoi(argv[4]);
    nz = (size_t)atoi(argv[5]);
    nvr = (size_t)(argc - 8);
    if (nx > MAX_SIZE || nz > MAX_SIZE || nvr > MAX_SIZE) {
        return fail("too many states, event indicators or value references");
    }
    for (size_t i = 0; i < nvr; i++) {
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
    result = simulate(&api, c, nx, nz, atof(argv[6]), atof(argv[7]), vrs, nvr);
    api.freeInstance(c);
    return result;
}
