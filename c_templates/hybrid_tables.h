/*
 * Types of the tables that hybrid_config.h (generated per hybrid FMU) fills in for the static
 * wrapper hybrid_wrapper.c. Every table has at least one slot, so a hybrid without, say,
 * aliases is still valid C; the N_* counts say how many slots are used.
 */
#ifndef HYBRID_TABLES_H
#define HYBRID_TABLES_H

#include <stddef.h>

#include "fmi2Functions.h"

/* A corrected state derivative der(x) of the original and the variables the wrapper adds. */
typedef struct {
    const char *name;              /* der(x) of the original FMU */
    fmi2ValueReference der_vr;     /* its value reference */
    size_t state_index;            /* index of x in the state vector */
    fmi2ValueReference p_ann_vr;   /* value references added by the wrapper */
    fmi2ValueReference p_fmu_vr;
    fmi2ValueReference ann_vr;
    double p_ann_start;
    double p_fmu_start;
    const char *p_ann_name;        /* names of the added variables, for messages */
    const char *p_fmu_name;
    const char *ann_name;
} Channel;

/* An output of the original that equals a channel's der(x). */
typedef struct {
    fmi2ValueReference vr;
    size_t channel;
} Alias;

#endif
