/* Bouncing ball: a ball dropped from height h0 bounces on the ground with restitution e. */
#ifndef BOUNCING_BALL_CONFIG_H
#define BOUNCING_BALL_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "bouncing_ball"
#define MODEL_GUID "{8c4e810f-3df3-4a00-8276-176fa3c9f000}"

#define NX 2 /* h, v */
#define NZ 1 /* h crossing zero */

#define HAS_DIRECTIONAL_DERIVATIVE

/* Value references, in the order of modelDescription.xml (index = vr + 1). */
typedef enum {
    VR_H = 0,
    VR_DER_H = 1,
    VR_V = 2,
    VR_DER_V = 3,
    VR_G = 4,
    VR_E = 5,
    VR_V_MIN = 6,
    VR_BOUNCES = 7
} ValueReference;

typedef struct {
    double h;     /* height above ground [m] */
    double v;     /* velocity, positive upwards [m/s] */
    double g;     /* gravitational acceleration [m/s2] */
    double e;     /* coefficient of restitution [1] */
    double v_min; /* below this rebound speed the ball stays on the ground [m/s] */
    int bounces;  /* number of impacts so far */
    bool at_rest; /* latched when a rebound would be slower than v_min */
} ModelData;

#endif
