/* Test model: exponential decay whose fmi2GetReal of der(x) calls the FMU's own exported
 * fmi2GetDerivatives, the way some generated FMUs reuse their API internally. */
#ifndef SELF_CALLING_CONFIG_H
#define SELF_CALLING_CONFIG_H

#define MODEL_IDENTIFIER "self_calling"
#define MODEL_GUID "{0b6f3f56-7c1e-4e43-9d0e-5a4a9c2f7e01}"

#define NX 1
#define NZ 0

typedef enum { VR_X = 0, VR_DER_X = 1, VR_K = 2 } ValueReference;

typedef struct {
    double x; /* decaying quantity [1] */
    double k; /* decay rate [1/s] */
} ModelData;

#endif
