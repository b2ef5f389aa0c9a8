/* A stair with no continuous states: a counter that steps up every `period` seconds. */
#ifndef STATELESS_CONFIG_H
#define STATELESS_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "stateless"
#define MODEL_GUID "{0d6a3f52-7c1e-4b8a-9e25-3f4c1b7d8a60}"

#define NX 0
#define NZ 0

typedef enum {
    VR_PERIOD = 0,
    VR_LEVEL = 1,
    VR_COUNTER = 2
} ValueReference;

typedef struct {
    double period; /* seconds between steps */
    double level;  /* counter as a Real output */
    int counter;   /* steps so far */
} ModelData;

#endif
