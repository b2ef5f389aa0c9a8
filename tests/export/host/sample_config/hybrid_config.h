/*
 * A hand-written configuration of the static wrapper c_templates/hybrid_wrapper.c, for compiling
 * and running it on its own: the bouncing ball example (examples/bouncing_ball) with der(v)
 * corrected by a linear "network" ann(h, v, der(v)) = 0.1 h - 0.2 v + 0.01 der(v), and the
 * output bounces read as an Integer input. The generated hybrid_config.h has the same shape.
 */
#ifndef HYBRID_CONFIG_H
#define HYBRID_CONFIG_H

#include "hybrid_tables.h"

#define HYBRID_GUID "{sample-hybrid-of-the-bouncing-ball}"
#define INNER_GUID "{8c4e810f-3df3-4a00-8276-176fa3c9f000}"
#define INNER_LIBRARY "bouncing_ball.so"
#define INNER_LIBRARY_WIN64 "bouncing_ball.dll"
#define N_STATES 2
#define N_EVENT_INDICATORS 1
#define N_CHANNELS 1
#define N_ANN_INPUTS 4
#define CAN_GET_AND_SET_FMU_STATE 1
#define CAN_SERIALIZE_FMU_STATE 1
#define CAN_NOT_USE_MEMORY_MANAGEMENT_FUNCTIONS 0
#define RUN_NETWORK sample_network

static void sample_network(const double *input, double *output) {
    output[0] = 0.1 * input[0] - 0.2 * input[1] + 0.01 * input[2] + 0.0 * input[3];
}

static const Channel CHANNELS[N_CHANNELS] = {
    {"der(v)", 3, 1, 8, 9, 10, 1.0, 1.0, "hybrid.v.p_ann", "hybrid.v.p_fmu", "hybrid.v.ann"},
};

#define N_ALIASES 0
static const Alias ALIASES[1] = {{0, 0}};

/* g set to its declared value: the override's path runs, the trajectory stays the original's. */
#define N_OVERRIDES 1
static const fmi2ValueReference OVERRIDE_VRS[] = {4};
static const fmi2Real OVERRIDE_VALUES[] = {9.81};

#define N_REAL_INPUTS 2
static const fmi2ValueReference REAL_INPUT_VRS[] = {0, 2};
static const size_t REAL_INPUT_POSITIONS[] = {0, 1};
#define N_INTEGER_INPUTS 1
static const fmi2ValueReference INTEGER_INPUT_VRS[] = {7};
static const size_t INTEGER_INPUT_POSITIONS[] = {3};
#define N_BOOLEAN_INPUTS 0
static const fmi2ValueReference BOOLEAN_INPUT_VRS[] = {0};
static const size_t BOOLEAN_INPUT_POSITIONS[] = {0};

#define N_DERIVATIVE_INPUTS 1
static const size_t DERIVATIVE_INPUT_STATES[] = {1};
static const size_t DERIVATIVE_INPUT_POSITIONS[] = {2};

#define N_INNER_LOG_CATEGORIES 1
static const char *const INNER_LOG_CATEGORIES[1] = {"logAll"};

#endif
