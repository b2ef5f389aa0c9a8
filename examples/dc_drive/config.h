/*
 * DC drive: a permanent-magnet DC motor with a PI speed controller following a speed
 * set-point profile against a load-torque profile; winding temperature and the electrical
 * energy drawn are states too.
 */
#ifndef DC_DRIVE_CONFIG_H
#define DC_DRIVE_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "dc_drive"
#define MODEL_GUID "{3b9d6c2e-5a41-4e8f-b7d0-c61f2a94e8d3}"

#define NX 5 /* current, speed, speed_error_integral, temperature, energy */
#define NZ 0 /* the profile's breakpoints are time events */

/* Continuous states, in this order; their value references are the same numbers. */
enum { X_CURRENT, X_SPEED, X_ERROR_INTEGRAL, X_TEMPERATURE, X_ENERGY };

typedef enum {
    VR_CURRENT = 0,
    VR_SPEED,
    VR_ERROR_INTEGRAL,
    VR_TEMPERATURE,
    VR_ENERGY,
    VR_DER_CURRENT,
    VR_DER_SPEED,
    VR_DER_ERROR_INTEGRAL,
    VR_DER_TEMPERATURE,
    VR_DER_ENERGY,
    /* outputs */
    VR_VOLTAGE,
    VR_POWER,
    /* locals */
    VR_SPEED_REFERENCE,
    VR_LOAD_TORQUE,
    VR_SPEED_ERROR,
    VR_MOTOR_TORQUE,
    VR_FRICTION_TORQUE,
    VR_RESISTANCE,
    VR_COPPER_LOSS,
    VR_COOLING_POWER,
    /* parameters */
    VR_NOMINAL_RESISTANCE = 100,
    VR_TEMPERATURE_COEFFICIENT,
    VR_REFERENCE_TEMPERATURE,
    VR_INDUCTANCE,
    VR_MOTOR_CONSTANT,
    VR_INERTIA,
    VR_VISCOUS_FRICTION,
    VR_HEAT_CAPACITY,
    VR_THERMAL_RESISTANCE,
    VR_AMBIENT_TEMPERATURE,
    VR_SPEED_GAIN,
    VR_INTEGRAL_GAIN,
    VR_PROFILE_REPEATS
} ValueReference;

typedef struct {
    double x[NX];

    double nominal_resistance;      /* [Ohm] winding resistance at the reference temperature */
    double temperature_coefficient; /* [1/K] of the winding resistance (copper) */
    double reference_temperature;   /* [K] */
    double inductance;              /* [H] */
    double motor_constant;          /* [N.m/A] = [V.s/rad], torque and back-EMF constant */
    double inertia;                 /* [kg.m2] motor and load */
    double viscous_friction;        /* [N.m.s/rad] bearing friction */
    double heat_capacity;           /* [J/K] winding and housing */
    double thermal_resistance;      /* [K/W] winding to ambient */
    double ambient_temperature;     /* [K] */
    double speed_gain;              /* [V.s/rad] proportional gain of the speed PI */
    double integral_gain;           /* [V/rad] integral gain of the speed PI */
    double profile_repeats;         /* [1] passes through the profile (1: once, then hold) */

    int segment; /* discrete state: profile segment [segment, segment + 1) holding the time */
    int pass;    /* discrete state: the pass through the profile holding the time */
} ModelData;

#endif
