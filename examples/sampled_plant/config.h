/* DC motor (continuous plant) under a discrete PI speed controller sampled every Ts. */
#ifndef SAMPLED_PLANT_CONFIG_H
#define SAMPLED_PLANT_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "sampled_plant"
#define MODEL_GUID "{5f0b2c61-93a4-4d1e-9a57-6b0c2d8e4a11}"

#define NX 2 /* armature current i, shaft speed w */
#define NZ 0 /* only time events */

/* Value references, in the order of modelDescription.xml (index = vr + 1). */
typedef enum {
    VR_I = 0,
    VR_DER_I = 1,
    VR_W = 2,
    VR_DER_W = 3,
    VR_SETPOINT = 4,
    VR_U = 5,
    VR_INTEGRAL = 6,
    VR_R = 7,
    VR_L = 8,
    VR_K = 9,
    VR_J = 10,
    VR_B = 11,
    VR_KP = 12,
    VR_KI = 13,
    VR_TS = 14,
    VR_U_MAX = 15,
    VR_SAMPLES = 16
} ValueReference;

typedef struct {
    /* plant */
    double i;        /* armature current [A] */
    double w;        /* shaft speed [rad/s] */
    double R;        /* armature resistance [Ohm] */
    double L;        /* armature inductance [H] */
    double K;        /* torque and back-EMF constant [N.m/A] */
    double J;        /* rotor inertia [kg.m2] */
    double b;        /* viscous friction [N.m.s/rad] */
    /* controller */
    double setpoint; /* speed set point, input [rad/s] */
    double u;        /* voltage held between samples [V] */
    double integral; /* integral part of the PI controller [V] */
    double Kp;       /* proportional gain [V.s/rad] */
    double Ki;       /* integral gain [V/rad] */
    double Ts;       /* sample period [s] */
    double u_max;    /* voltage limit [V] */
    int samples;     /* number of controller samples taken */
} ModelData;

#endif
