/* Test model: decay with an output y = 2 x that is recomputed lazily. */
#ifndef LAZY_OUTPUTS_CONFIG_H
#define LAZY_OUTPUTS_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "lazy_outputs"
#define MODEL_GUID "{3e7d2a91-5f64-4b0c-9c1a-7b2e8d4f6a10}"

#define NX 1
#define NZ 0

typedef enum { VR_X = 0, VR_DER_X = 1, VR_Y = 2 } ValueReference;

typedef struct {
    double x;           /* decaying quantity [1] */
    bool need_update;   /* the inputs changed since the last evaluation */
    double der_x;       /* cached results of the last evaluation */
    double y;
} ModelData;

#endif
