/*
 * Minimal FMI 2.0 Model-Exchange host for the hybrid FMU tests.
 *
 *   fmu_host LIBRARY GUID RESOURCE_URI N_STATES N_INDICATORS CYCLES STEPS STEP_SIZE [VR...]
 *
 * Loads LIBRARY with RTLD_NOW | RTLD_GLOBAL (so its fmi2* symbols are global, the case the
 * wrapper's RTLD_DEEPBIND guards against; RTLD_LOCAL if FMU_HOST_RTLD_LOCAL is set, for a
 * wrapper built without RTLD_DEEPBIND under the sanitizers), then CYCLES times: instantiate, initialise, STEPS
 * forward-Euler steps with fmpy's arithmetic (dt = t_next - t, events at step ends), an FMU
 * state round trip (get, serialize, deserialize, set, free) when the FMU supports it,
 * terminate, free. Prints the states and the Real values of the given value references after
 * the last cycle, one per line with 17 significant digits. Exit code 0 when every call
 * succeeded.
 */
#include <dlfcn.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

#define MAX_SIZE 64

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

static void logger(fmi2ComponentEnvironment env, fmi2String name, fmi2Status status, fmi2String category,
                   fmi2String message, ...) {
    va_list args;
    (void)env;
    if (status < fmi2Error) {
        return;
    }
    fprintf(stderr, "[%s] [%s] ", name ? name : "", category ? category : "");
    va_start(args, message);
    vfprintf(stderr, message, args);
    va_end(args);
    fputc('\n', stderr);
}

static void *symbol(void *library, const char *name) {
    void *address = dlsym(library, name);
    if (address == NULL) {
        fprintf(stderr, "missing symbol %s\n", name);
        exit(2);
    }
    return address;
}

#define CHECK(call)                                                                 \
    do {                                                                            \
        if ((call) > fmi2Warning) {                                                 \
            fprintf(stderr, "%s failed at line %d\n", #call, __LINE__);             \
            exit(1);                                                                \
        }                                                                           \
    } while (0)

static void event_iteration(const Api *api, fmi2Component c) {
    fmi2EventInfo info;
    do {
        info.newDiscreteStatesNeeded = fmi2False;
        CHECK(api->newDiscreteStates(c, &info));
    } while (info.newDiscreteStatesNeeded && !info.terminateSimulation);
}

static void state_round_trip(const Api *api, fmi2Component c) {
    fmi2FMUstate state = NULL, copy = NULL;
    size_t size = 0;
    fmi2Byte *bytes;
    CHECK(api->getFMUstate(c, &state));
    CHECK(api->getFMUstate(c, &state)); /* overwrite in place */
    CHECK(api->serializedFMUstateSize(c, state, &size));
    bytes = malloc(size);
    CHECK(api->serializeFMUstate(c, state, bytes, size));
    CHECK(api->deSerializeFMUstate(c, bytes, size, &copy));
    CHECK(api->setFMUstate(c, copy));
    CHECK(api->freeFMUstate(c, &copy));
    CHECK(api->freeFMUstate(c, &state));
    free(bytes);
}

int main(int argc, char **argv) {
    if (argc < 9) {
        fprintf(stderr, "usage: %s LIBRARY GUID RESOURCE_URI N_STATES N_INDICATORS CYCLES STEPS STEP_SIZE [VR...]\n",
                argv[0]);
        return 2;
    }
    const char *guid = argv[2], *resources = argv[3];
    size_t nx = (size_t)atoi(argv[4]), nz = (size_t)atoi(argv[5]);
    int cycles = atoi(argv[6]), steps = atoi(argv[7]);
    double h = atof(argv[8]);
    size_t nvr = (size_t)(argc - 9);
    fmi2ValueReference vrs[MAX_SIZE];
    double x[MAX_SIZE], dx[MAX_SIZE], z[MAX_SIZE], z_previous[MAX_SIZE], values[MAX_SIZE];
    if (nx > MAX_SIZE || nz > MAX_SIZE || nvr > MAX_SIZE) {
        fprintf(stderr, "too many states, indicators or value references\n");
        return 2;
    }
    for (size_t i = 0; i < nvr; i++) {
        vrs[i] = (fmi2ValueReference)strtoul(argv[9 + i], NULL, 10);
    }

    void *library = dlopen(argv[1], RTLD_NOW | (getenv("FMU_HOST_RTLD_LOCAL") ? RTLD_LOCAL : RTLD_GLOBAL));
    if (library == NULL) {
        fprintf(stderr, "dlopen failed: %s\n", dlerror());
        return 2;
    }
    Api api;
    api.instantiate = symbol(library, "fmi2Instantiate");
    api.freeInstance = symbol(library, "fmi2FreeInstance");
    api.setupExperiment = symbol(library, "fmi2SetupExperiment");
    api.enterInitializationMode = symbol(library, "fmi2EnterInitializationMode");
    api.exitInitializationMode = symbol(library, "fmi2ExitInitializationMode");
    api.newDiscreteStates = symbol(library, "fmi2NewDiscreteStates");
    api.enterContinuousTimeMode = symbol(library, "fmi2EnterContinuousTimeMode");
    api.enterEventMode = symbol(library, "fmi2EnterEventMode");
    api.getContinuousStates = symbol(library, "fmi2GetContinuousStates");
    api.setContinuousStates = symbol(library, "fmi2SetContinuousStates");
    api.getDerivatives = symbol(library, "fmi2GetDerivatives");
    api.getEventIndicators = symbol(library, "fmi2GetEventIndicators");
    api.setTime = symbol(library, "fmi2SetTime");
    api.completedIntegratorStep = symbol(library, "fmi2CompletedIntegratorStep");
    api.getReal = symbol(library, "fmi2GetReal");
    api.getFMUstate = symbol(library, "fmi2GetFMUstate");
    api.setFMUstate = symbol(library, "fmi2SetFMUstate");
    api.freeFMUstate = symbol(library, "fmi2FreeFMUstate");
    api.serializedFMUstateSize = symbol(library, "fmi2SerializedFMUstateSize");
    api.serializeFMUstate = symbol(library, "fmi2SerializeFMUstate");
    api.deSerializeFMUstate = symbol(library, "fmi2DeSerializeFMUstate");
    api.terminate = symbol(library, "fmi2Terminate");
    int with_state = getenv("FMU_HOST_FMU_STATE") != NULL;

    fmi2CallbackFunctions callbacks = {logger, calloc, free, NULL, NULL};
    for (int cycle = 0; cycle < cycles; cycle++) {
        fmi2Component c = api.instantiate("host", fmi2ModelExchange, guid, resources, &callbacks, fmi2False,
                                          fmi2False);
        if (c == NULL) {
            fprintf(stderr, "fmi2Instantiate failed\n");
            return 1;
        }
        double t = 0.0;
        fmi2Boolean enter_event = fmi2False, terminate = fmi2False;
        CHECK(api.setupExperiment(c, fmi2False, 0.0, t, fmi2False, 0.0));
        CHECK(api.enterInitializationMode(c));
        CHECK(api.exitInitializationMode(c));
        event_iteration(&api, c);
        CHECK(api.enterContinuousTimeMode(c));
        CHECK(api.getEventIndicators(c, z, nz));
        for (int n = 0; n < steps; n++) {
            double t_next = (n + 1) * h;
            int state_event = 0;
            CHECK(api.getContinuousStates(c, x, nx));
            CHECK(api.getDerivatives(c, dx, nx));
            for (size_t i = 0; i < nx; i++) {
                x[i] += (t_next - t) * dx[i];
            }
            CHECK(api.setContinuousStates(c, x, nx));
            memcpy(z_previous, z, sizeof(double) * nz);
            CHECK(api.getEventIndicators(c, z, nz));
            for (size_t i = 0; i < nz; i++) {
                state_event |= (z_previous[i] < 0 && z[i] >= 0) || (z_previous[i] > 0 && z[i] <= 0);
            }
            t = t_next;
            CHECK(api.setTime(c, t));
            CHECK(api.completedIntegratorStep(c, fmi2True, &enter_event, &terminate));
            if (state_event || enter_event) {
                CHECK(api.enterEventMode(c));
                event_iteration(&api, c);
                CHECK(api.enterContinuousTimeMode(c));
            }
            if (with_state && n == steps / 2) {
                state_round_trip(&api, c);
            }
        }
        CHECK(api.getContinuousStates(c, x, nx));
        CHECK(api.getReal(c, vrs, nvr, values));
        CHECK(api.terminate(c));
        api.freeInstance(c);
    }
    for (size_t i = 0; i < nx; i++) {
        printf("%.17g\n", x[i]);
    }
    for (size_t i = 0; i < nvr; i++) {
        printf("%.17g\n", values[i]);
    }
    dlclose(library);
    return 0;
}
