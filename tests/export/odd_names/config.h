/* Test model with unusual but legal variable names: two coupled decays. */
#ifndef ODD_NAMES_CONFIG_H
#define ODD_NAMES_CONFIG_H

#define MODEL_IDENTIFIER "odd_names"
#define MODEL_GUID "{5d0c9a52-3b7e-4f11-a6c2-8e1f0d4b7a93}"

#define NX 2
#define NZ 0

/* 'my var', der('my var'), a[1], der(a[1]), the rate k, the output y */
typedef enum { VR_MY_VAR = 0, VR_DER_MY_VAR = 1, VR_A1 = 2, VR_DER_A1 = 3, VR_K = 4, VR_Y = 5 } ValueReference;

typedef struct {
    double my_var;
    double a1;
    double k;
} ModelData;

#endif
