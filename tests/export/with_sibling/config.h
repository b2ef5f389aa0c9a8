/* Test model: exponential decay whose rate comes from a second shared library. */
#ifndef WITH_SIBLING_CONFIG_H
#define WITH_SIBLING_CONFIG_H

#define MODEL_IDENTIFIER "with_sibling"
#define MODEL_GUID "{9a1f5b3e-2c4d-4e8f-b6a7-0d1c2e3f4a5b}"

#define NX 1
#define NZ 0

typedef enum { VR_X = 0, VR_DER_X = 1 } ValueReference;

typedef struct {
    double x; /* decaying quantity [1] */
} ModelData;

#endif
