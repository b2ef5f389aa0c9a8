/*
 * A calibrated FMU: the original FMU's binary, unchanged, with some parameters set to calibrated
 * values. Configured by -D definitions (see fmubuilder/export/calibrated.py):
 *
 *   CALIBRATED_GUID, INNER_GUID    the GUIDs of this FMU and of the original
 *   INNER_LIBRARY                  the original's binary, beside this library ("<id>.so")
 *   N_OVERRIDES, OVERRIDE_VRS, OVERRIDE_VALUES, OVERRIDE_NAMES   the calibrated parameters
 *
 * When this library is loaded it loads the original's binary from its own folder, privately
 * (RTLD_LOCAL | RTLD_DEEPBIND: two FMUs with the same function names never mix, and the original
 * binds its own calls to itself). Every FMI function is forwarded unchanged, with the original's
 * component as this FMU's, except two: fmi2Instantiate sets the calibrated values before the
 * importer sees the instance, and fmi2Reset sets them again (a reset returns the original to its
 * own start values). The importer may still set the parameters itself, as on any FMU.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"

static const fmi2ValueReference OVERRIDE_VR_TABLE[N_OVERRIDES] = OVERRIDE_VRS;
static const fmi2Real OVERRIDE_VALUE_TABLE[N_OVERRIDES] = OVERRIDE_VALUES;
static const char *const OVERRIDE_NAME_TABLE[N_OVERRIDES] = OVERRIDE_NAMES;

/* Every FMI 2.0 function of the original, looked up by name. */
#define INNER_FUNCTIONS(X) \
    X(fmi2GetTypesPlatform) X(fmi2GetVersion) X(fmi2SetDebugLogging) X(fmi2Instantiate) X(fmi2FreeInstance) \
    X(fmi2SetupExperiment) X(fmi2EnterInitializationMode) X(fmi2ExitInitializationMode) X(fmi2Terminate) \
    X(fmi2Reset) X(fmi2GetReal) X(fmi2GetInteger) X(fmi2GetBoolean) X(fmi2GetString) X(fmi2SetReal) \
    X(fmi2SetInteger) X(fmi2SetBoolean) X(fmi2SetString) X(fmi2GetFMUstate) X(fmi2SetFMUstate) \
    X(fmi2FreeFMUstate) X(fmi2SerializedFMUstateSize) X(fmi2SerializeFMUstate) X(fmi2DeSerializeFMUstate) \
    X(fmi2GetDirectionalDerivative) X(fmi2EnterEventMode) X(fmi2NewDiscreteStates) \
    X(fmi2EnterContinuousTimeMode) X(fmi2CompletedIntegratorStep) X(fmi2SetTime) X(fmi2SetContinuousStates) \
    X(fmi2GetDerivatives) X(fmi2GetEventIndicators) X(fmi2GetContinuousStates) \
    X(fmi2GetNominalsOfContinuousStates) X(fmi2SetRealInputDerivatives) X(fmi2GetRealOutputDerivatives) \
    X(fmi2DoStep) X(fmi2CancelStep) X(fmi2GetStatus) X(fmi2GetRealStatus) X(fmi2GetIntegerStatus) \
    X(fmi2GetBooleanStatus) X(fmi2GetStringStatus)

#define FIELD(f) f##TYPE *f;
static struct { INNER_FUNCTIONS(FIELD) } INNER;
#undef FIELD

/* Empty when the original loaded; else why it did not (reported at fmi2Instantiate). */
static char LOAD_ERROR[4400];

__attribute__((constructor)) static void load_inner(void) {
    Dl_info self;
    char path[4096];
    if (dladdr((const void *)OVERRIDE_VR_TABLE, &self) == 0 || self.dli_fname == NULL) {
        snprintf(LOAD_ERROR, sizeof(LOAD_ERROR), "cannot locate the calibrated FMU's own library");
        return;
    }
    snprintf(path, sizeof(path), "%s", self.dli_fname);
    char *slash = strrchr(path, '/');
    size_t folder = slash ? (size_t)(slash - path + 1) : 0;
    snprintf(path + folder, sizeof(path) - folder, "%s", INNER_LIBRARY);
    void *handle = dlopen(path, RTLD_NOW | RTLD_LOCAL | RTLD_DEEPBIND);
    if (handle == NULL) {
        snprintf(LOAD_ERROR, sizeof(LOAD_ERROR), "cannot load the original FMU's binary: %s", dlerror());
        return;
    }
#define LOOK_UP(f)                                                                                   \
    if ((INNER.f = (f##TYPE *)dlsym(handle, #f)) == NULL) {                                          \
        snprintf(LOAD_ERROR, sizeof(LOAD_ERROR), "the original FMU's binary %s does not export %s", path, #f); \
        return;                                                                                      \
    }
    INNER_FUNCTIONS(LOOK_UP)
#undef LOOK_UP
}

static void log_error(const fmi2CallbackFunctions *functions, fmi2String name, const char *message) {
    if (functions != NULL && functions->logger != NULL) {
        functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError", "%s", message);
    }
}

static fmi2Status apply_calibration(fmi2Component c) {
    return INNER.fmi2SetReal(c, OVERRIDE_VR_TABLE, N_OVERRIDES, OVERRIDE_VALUE_TABLE);
}

FMI2_Export fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                                          fmi2String fmuResourceLocation,
                                          const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                                          fmi2Boolean loggingOn) {
    char message[4500];
    if (LOAD_ERROR[0] != '\0') {
        snprintf(message, sizeof(message), "fmi2Instantiate: %s.", LOAD_ERROR);
        log_error(functions, instanceName, message);
        return NULL;
    }
    if (fmuGUID == NULL || strcmp(fmuGUID, CALIBRATED_GUID) != 0) {
        snprintf(message, sizeof(message), "fmi2Instantiate: GUID '%s' does not match this FMU's %s.",
                 fmuGUID ? fmuGUID : "(null)", CALIBRATED_GUID);
        log_error(functions, instanceName, message);
        return NULL;
    }
    fmi2Component c = INNER.fmi2Instantiate(instanceName, fmuType, INNER_GUID, fmuResourceLocation, functions,
                                            visible, loggingOn);
    if (c != NULL && apply_calibration(c) > fmi2Warning) {
        snprintf(message, sizeof(message), "fmi2Instantiate: the original FMU refused the calibrated value of %s.",
                 OVERRIDE_NAME_TABLE[0]);
        log_error(functions, instanceName, message);
        INNER.fmi2FreeInstance(c);
        return NULL;
    }
    return c;
}

FMI2_Export fmi2Status fmi2Reset(fmi2Component c) {
    if (LOAD_ERROR[0] != '\0') {
        return fmi2Error;
    }
    fmi2Status status = INNER.fmi2Reset(c);
    if (status > fmi2Warning) {
        return status;
    }
    fmi2Status applied = apply_calibration(c);
    return applied > status ? applied : status;
}

/* Everything else goes to the original as it is. Without an original (LOAD_ERROR) there is no
 * instance, so only the two functions an importer may call before fmi2Instantiate need a guard. */
FMI2_Export const char *fmi2GetTypesPlatform(void) {
    return INNER.fmi2GetTypesPlatform ? INNER.fmi2GetTypesPlatform() : fmi2TypesPlatform;
}

FMI2_Export const char *fmi2GetVersion(void) {
    return INNER.fmi2GetVersion ? INNER.fmi2GetVersion() : fmi2Version;
}

FMI2_Export void fmi2FreeInstance(fmi2Component c) { INNER.fmi2FreeInstance(c); }

#define FORWARD(f, params, args) \
    FMI2_Export fmi2Status f params { return INNER.f args; }

typedef const fmi2ValueReference VRS[];
FORWARD(fmi2SetDebugLogging, (fmi2Component c, fmi2Boolean on, size_t n, const fmi2String categories[]),
        (c, on, n, categories))
FORWARD(fmi2SetupExperiment, (fmi2Component c, fmi2Boolean tolerance_defined, fmi2Real tolerance,
                              fmi2Real start, fmi2Boolean stop_defined, fmi2Real stop),
        (c, tolerance_defined, tolerance, start, stop_defined, stop))
FORWARD(fmi2EnterInitializationMode, (fmi2Component c), (c))
FORWARD(fmi2ExitInitializationMode, (fmi2Component c), (c))
FORWARD(fmi2Terminate, (fmi2Component c), (c))
FORWARD(fmi2GetReal, (fmi2Component c, VRS vr, size_t n, fmi2Real v[]), (c, vr, n, v))
FORWARD(fmi2GetInteger, (fmi2Component c, VRS vr, size_t n, fmi2Integer v[]), (c, vr, n, v))
FORWARD(fmi2GetBoolean, (fmi2Component c, VRS vr, size_t n, fmi2Boolean v[]), (c, vr, n, v))
FORWARD(fmi2GetString, (fmi2Component c, VRS vr, size_t n, fmi2String v[]), (c, vr, n, v))
FORWARD(fmi2SetReal, (fmi2Component c, VRS vr, size_t n, const fmi2Real v[]), (c, vr, n, v))
FORWARD(fmi2SetInteger, (fmi2Component c, VRS vr, size_t n, const fmi2Integer v[]), (c, vr, n, v))
FORWARD(fmi2SetBoolean, (fmi2Component c, VRS vr, size_t n, const fmi2Boolean v[]), (c, vr, n, v))
FORWARD(fmi2SetString, (fmi2Component c, VRS vr, size_t n, const fmi2String v[]), (c, vr, n, v))
FORWARD(fmi2GetFMUstate, (fmi2Component c, fmi2FMUstate *s), (c, s))
FORWARD(fmi2SetFMUstate, (fmi2Component c, fmi2FMUstate s), (c, s))
FORWARD(fmi2FreeFMUstate, (fmi2Component c, fmi2FMUstate *s), (c, s))
FORWARD(fmi2SerializedFMUstateSize, (fmi2Component c, fmi2FMUstate s, size_t *size), (c, s, size))
FORWARD(fmi2SerializeFMUstate, (fmi2Component c, fmi2FMUstate s, fmi2Byte bytes[], size_t size),
        (c, s, bytes, size))
FORWARD(fmi2DeSerializeFMUstate, (fmi2Component c, const fmi2Byte bytes[], size_t size, fmi2FMUstate *s),
        (c, bytes, size, s))
FORWARD(fmi2GetDirectionalDerivative, (fmi2Component c, VRS unknown, size_t n_unknown, VRS known,
                                       size_t n_known, const fmi2Real dv_known[], fmi2Real dv_unknown[]),
        (c, unknown, n_unknown, known, n_known, dv_known, dv_unknown))
FORWARD(fmi2EnterEventMode, (fmi2Component c), (c))
FORWARD(fmi2NewDiscreteStates, (fmi2Component c, fmi2EventInfo *info), (c, info))
FORWARD(fmi2EnterContinuousTimeMode, (fmi2Component c), (c))
FORWARD(fmi2CompletedIntegratorStep, (fmi2Component c, fmi2Boolean no_set_prior, fmi2Boolean *enter_event_mode,
                                      fmi2Boolean *terminate),
        (c, no_set_prior, enter_event_mode, terminate))
FORWARD(fmi2SetTime, (fmi2Component c, fmi2Real t), (c, t))
FORWARD(fmi2SetContinuousStates, (fmi2Component c, const fmi2Real x[], size_t n), (c, x, n))
FORWARD(fmi2GetDerivatives, (fmi2Component c, fmi2Real dx[], size_t n), (c, dx, n))
FORWARD(fmi2GetEventIndicators, (fmi2Component c, fmi2Real z[], size_t n), (c, z, n))
FORWARD(fmi2GetContinuousStates, (fmi2Component c, fmi2Real x[], size_t n), (c, x, n))
FORWARD(fmi2GetNominalsOfContinuousStates, (fmi2Component c, fmi2Real nominal[], size_t n), (c, nominal, n))
FORWARD(fmi2SetRealInputDerivatives, (fmi2Component c, VRS vr, size_t n, const fmi2Integer order[],
                                      const fmi2Real v[]), (c, vr, n, order, v))
FORWARD(fmi2GetRealOutputDerivatives, (fmi2Component c, VRS vr, size_t n, const fmi2Integer order[],
                                       fmi2Real v[]), (c, vr, n, order, v))
FORWARD(fmi2DoStep, (fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean no_set_prior), (c, t, h, no_set_prior))
FORWARD(fmi2CancelStep, (fmi2Component c), (c))
FORWARD(fmi2GetStatus, (fmi2Component c, const fmi2StatusKind s, fmi2Status *v), (c, s, v))
FORWARD(fmi2GetRealStatus, (fmi2Component c, const fmi2StatusKind s, fmi2Real *v), (c, s, v))
FORWARD(fmi2GetIntegerStatus, (fmi2Component c, const fmi2StatusKind s, fmi2Integer *v), (c, s, v))
FORWARD(fmi2GetBooleanStatus, (fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v), (c, s, v))
FORWARD(fmi2GetStringStatus, (fmi2Component c, const fmi2StatusKind s, fmi2String *v), (c, s, v))
