/* The floor of a fixed-step simulation: a plain C loop over an FMI 2.0 Model-Exchange binary, with
 * nothing but what any simulator must do. bench_core.py builds and runs it beside the engine.
 *
 *   plain_fmu_loop LIBRARY GUID RESOURCES_URI STOP STEP OUTPUT_EVERY NX NZ [VR ...]
 *
 * Classical RK4 at STEP from 0 to STOP, each step ending at the next time event if earlier; the
 * event indicators and fmi2CompletedIntegratorStep after every step; event mode (with the event
 * iteration) at every time event, at a sign change of an indicator (the step redone to the
 * crossing by bisecting its length) and at a step event; every OUTPUT_EVERY-th step the listed Real variables read with fmi2GetReal.
 * Prints the seconds from fmi2Instantiate to fmi2FreeInstance, the steps, the events and the
 * final states. */
#define _POSIX_C_SOURCE 200809L
#include <dlfcn.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "fmi2Functions.h"

#define LOAD(name) fmi2##name##TYPE *name = (fmi2##name##TYPE *)dlsym(library, "fmi2" #name); \
    if (name == NULL) { fprintf(stderr, "missing fmi2" #name "\n"); return 2; }
#define CHECK(call) if ((call) > fmi2Warning) { fprintf(stderr, "%s failed at t=%g\n", #call, t); return 3; }

static void logger(fmi2ComponentEnvironment env, fmi2String name, fmi2Status status, fmi2String category,
                   fmi2String message, ...)
{
    (void)env; (void)name; (void)status; (void)category; (void)message;
}

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

static int any_crossed(const double *z, const double *z_new, size_t nz)
{
    for (size_t i = 0; i < nz; ++i) {
        if ((z[i] < 0.0 && z_new[i] >= 0.0) || (z[i] > 0.0 && z_new[i] <= 0.0)) {
            return 1;
        }
    }
    return 0;
}

/* One classical RK4 step of length h from (t, x0) into x. */
static fmi2Status rk4(fmi2Component c, fmi2SetTimeTYPE *SetTime, fmi2SetContinuousStatesTYPE *SetStates,
                      fmi2GetDerivativesTYPE *GetDerivatives, double t, const double *x0, double h, size_t nx,
                      double *x, double *stage, double **k)
{
    const double offsets[4] = {0.0, 0.5 * h, 0.5 * h, h};
    fmi2Status status = fmi2OK;
    for (int s = 0; s < 4 && status <= fmi2Warning; ++s) {
        for (size_t i = 0; i < nx; ++i) {
            stage[i] = s == 0 ? x0[i] : x0[i] + offsets[s] * k[s - 1][i];
        }
        status = SetTime(c, t + offsets[s]);
        if (nx && status <= fmi2Warning) {
            status = SetStates(c, stage, nx);
        }
        if (nx && status <= fmi2Warning) {
            status = GetDerivatives(c, k[s], nx);
        }
    }
    for (size_t i = 0; i < nx; ++i) {
        x[i] = x0[i] + h / 6.0 * (k[0][i] + 2.0 * (k[1][i] + k[2][i]) + k[3][i]);
    }
    return status;
}

/* The event indicators at (t, x). */
static fmi2Status indicators(fmi2Component c, fmi2SetTimeTYPE *SetTime, fmi2SetContinuousStatesTYPE *SetStates,
                             fmi2GetEventIndicatorsTYPE *GetEventIndicators, double t, const double *x, size_t nx,
                             double *z, size_t nz)
{
    fmi2Status status = SetTime(c, t);
    if (nx && status <= fmi2Warning) {
        status = SetStates(c, x, nx);
    }
    return status <= fmi2Warning ? GetEventIndicators(c, z, nz) : status;
}

int main(int argc, char **argv)
{
    if (argc < 9) {
        fprintf(stderr, "usage: plain_fmu_loop LIBRARY GUID RESOURCES_URI STOP STEP OUTPUT_EVERY NX NZ [VR ...]\n");
        return 1;
    }
    double t = 0.0, stop = atof(argv[4]), step = atof(argv[5]);
    long output_every = atol(argv[6]);
    size_t nx = (size_t)atol(argv[7]), nz = (size_t)atol(argv[8]), nvr = (size_t)(argc - 9);
    void *library = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
    if (library == NULL) {
        fprintf(stderr, "%s\n", dlerror());
        return 2;
    }
    LOAD(Instantiate) LOAD(FreeInstance) LOAD(SetupExperiment) LOAD(EnterInitializationMode)
    LOAD(ExitInitializationMode) LOAD(Terminate) LOAD(NewDiscreteStates) LOAD(EnterEventMode)
    LOAD(EnterContinuousTimeMode) LOAD(CompletedIntegratorStep) LOAD(SetTime) LOAD(SetContinuousStates)
    LOAD(GetDerivatives) LOAD(GetEventIndicators) LOAD(GetContinuousStates) LOAD(GetReal)

    fmi2ValueReference *vrs = calloc(nvr + 1, sizeof(fmi2ValueReference));
    double *values = calloc(nvr + 1, sizeof(double));
    double *x = calloc(nx + 1, sizeof(double)), *stage = calloc(nx + 1, sizeof(double));
    double *k[4];
    for (int i = 0; i < 4; ++i) {
        k[i] = calloc(nx + 1, sizeof(double));
    }
    double *z = calloc(nz + 1, sizeof(double)), *z_new = calloc(nz + 1, sizeof(double));
    for (size_t i = 0; i < nvr; ++i) {
        vrs[i] = (fmi2ValueReference)atol(argv[9 + i]);
    }
    fmi2CallbackFunctions callbacks = {logger, calloc, free, NULL, NULL};
    fmi2EventInfo info;
    long steps = 0, events = 0;
    double checksum = 0.0;

    double started = now();
    fmi2Component c = Instantiate("floor", fmi2ModelExchange, argv[2], argv[3], &callbacks, fmi2False, fmi2False);
    if (c == NULL) {
        fprintf(stderr, "fmi2Instantiate failed\n");
        return 3;
    }
    CHECK(SetupExperiment(c, fmi2False, 0.0, 0.0, fmi2True, stop));
    CHECK(EnterInitializationMode(c));
    CHECK(ExitInitializationMode(c));
    int event_mode = 1;
    for (;;) {
        if (event_mode) {       /* the event iteration, then back to continuous time */
            do {
                info.newDiscreteStatesNeeded = fmi2True;
                CHECK(NewDiscreteStates(c, &info));
            } while (info.newDiscreteStatesNeeded && !info.terminateSimulation);
            if (info.terminateSimulation) {
                break;
            }
            CHECK(EnterContinuousTimeMode(c));
            if (nx) {
                CHECK(GetContinuousStates(c, x, nx));
            }
            if (nz) {
                CHECK(GetEventIndicators(c, z, nz));
            }
            event_mode = 0;
        }
        if (t >= stop - 1e-12 * stop) {
            break;
        }
        double h = step, next = info.nextEventTimeDefined ? info.nextEventTime : INFINITY;
        h = stop - t < h ? stop - t : h;
        h = next - t < h ? next - t : h;
        double x_old[nx + 1], t_old = t;
        for (size_t i = 0; i < nx; ++i) {
            x_old[i] = x[i];
        }
        CHECK(rk4(c, SetTime, SetContinuousStates, GetDerivatives, t_old, x_old, h, nx, x, stage, k));
        t = h == step ? t + step : (h == next - t ? next : t + h);
        steps += 1;
        int crossed = 0;
        if (nz) {
            CHECK(indicators(c, SetTime, SetContinuousStates, GetEventIndicators, t, x, nx, z_new, nz));
            crossed = any_crossed(z, z_new, nz);
            if (crossed) {  /* the step redone to the crossing, its length bisected to 1e-12 s */
                double lo = 0.0, hi = h;
                while (hi - lo > 1e-12) {
                    double mid = 0.5 * (lo + hi);
                    CHECK(rk4(c, SetTime, SetContinuousStates, GetDerivatives, t_old, x_old, mid, nx, x, stage, k));
                    CHECK(indicators(c, SetTime, SetContinuousStates, GetEventIndicators, t_old + mid, x, nx, z_new, nz));
                    if (any_crossed(z, z_new, nz)) {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                t = t_old + hi;
                CHECK(rk4(c, SetTime, SetContinuousStates, GetDerivatives, t_old, x_old, hi, nx, x, stage, k));
                CHECK(indicators(c, SetTime, SetContinuousStates, GetEventIndicators, t, x, nx, z_new, nz));
            }
            for (size_t i = 0; i < nz; ++i) {
                z[i] = z_new[i];
            }
        } else {
            CHECK(SetTime(c, t));
            if (nx) {
                CHECK(SetContinuousStates(c, x, nx));
            }
        }
        fmi2Boolean step_event = fmi2False, terminate = fmi2False;
        CHECK(CompletedIntegratorStep(c, fmi2True, &step_event, &terminate));
        if (terminate) {
            break;
        }
        if (nvr && steps % output_every == 0) {
            CHECK(GetReal(c, vrs, nvr, values));
            checksum += values[0];
        }
        if (crossed || step_event || t >= next - 1e-12 * stop) {
            CHECK(EnterEventMode(c));
            event_mode = 1;
            events += 1;
        }
    }
    CHECK(Terminate(c));
    FreeInstance(c);
    double elapsed = now() - started;
    printf("seconds %.6f steps %ld events %ld checksum %.17g\n", elapsed, steps, events, checksum);
    printf("states");
    for (size_t i = 0; i < nx; ++i) {
        printf(" %.17g", x[i]);
    }
    printf("\n");
    return 0;
}
