/*
 * Vehicle longitudinal dynamics model (VLDM) of an electric Smart fortwo following a
 * driving cycle: sampled PI driver, motor with full-load curve and loss maps, brakes,
 * road loads, standstill handling and the electrical energy drawn from the battery.
 */
#ifndef VLDM_CONFIG_H
#define VLDM_CONFIG_H

#include <stdbool.h>

#define MODEL_IDENTIFIER "vldm"
#define MODEL_GUID "{6f3c2a1e-8b4d-4f7a-9c55-0d2e7b1a9f41}"

#define NX 6  /* continuous states */
#define NZ 12 /* event indicators (listed in model.c) */

/* Continuous states, in this order (also their value references). */
enum {
    X_THROTTLE_INTEGRATOR,
    X_BRAKE_INTEGRATOR,
    X_CYCLE_POSITION,
    X_POSITION,
    X_SPEED,
    X_ENERGY
};

/* Real value references. The first six are the states, the next six their derivatives. */
typedef enum {
    VR_THROTTLE_INTEGRATOR = 0,
    VR_BRAKE_INTEGRATOR,
    VR_CYCLE_POSITION,
    VR_POSITION,
    VR_SPEED,
    VR_ENERGY,
    VR_DER_THROTTLE_INTEGRATOR,
    VR_DER_BRAKE_INTEGRATOR,
    VR_DER_CYCLE_POSITION,
    VR_DER_POSITION,
    VR_DER_SPEED,
    VR_DER_ENERGY,
    /* outputs */
    VR_ACCELERATION,
    VR_POWER,
    /* locals */
    VR_TARGET_SPEED,
    VR_SPEED_ERROR,
    VR_HELD_ERROR,
    VR_THROTTLE,
    VR_BRAKE,
    VR_MOTOR_SPEED,
    VR_MOTOR_TORQUE_DEMAND,
    VR_MOTOR_TORQUE_LIMIT,
    VR_MOTOR_TORQUE,
    VR_BRAKE_TORQUE,
    VR_DRIVE_FORCE,
    VR_BRAKE_FORCE,
    VR_ROLLING_RESISTANCE_FORCE,
    VR_AIR_RESISTANCE_FORCE,
    VR_SLOPE_FORCE,
    VR_RESISTANCE_FORCE,
    VR_MOTOR_POWER,
    VR_POWER_ELECTRONICS_LOSS,
    VR_POWER_DEMAND,
    /* parameters */
    VR_MASS = 100,
    VR_MASS_FACTOR,
    VR_ROLLING_COEFFICIENT,
    VR_DRAG_COEFFICIENT,
    VR_FRONTAL_AREA,
    VR_AIR_DENSITY,
    VR_GRAVITY,
    VR_SLOPE,
    VR_WHEEL_RADIUS,
    VR_GEAR_RATIO,
    VR_GEAR_EFFICIENCY,
    VR_MAX_MOTOR_TORQUE,
    VR_MAX_BRAKE_TORQUE,
    VR_AUX_POWER,
    VR_MAX_POWER,
    VR_MIN_POWER,
    VR_THROTTLE_P,
    VR_THROTTLE_I,
    VR_BRAKE_P,
    VR_BRAKE_I,
    VR_HYSTERESIS,
    VR_SAMPLE_PERIOD
} RealVR;

typedef enum { VR_CYCLE = 200 } IntegerVR;

typedef enum {
    VR_THROTTLE_ACTIVE = 300,
    VR_BRAKE_ACTIVE,
    VR_STANDSTILL
} BooleanVR;

typedef struct {
    double x[NX];

    /* physical parameters */
    double mass;              /* [kg] */
    double mass_factor;       /* [1] rotating-mass factor on the vehicle mass */
    double rolling_coefficient;
    double drag_coefficient;
    double frontal_area;      /* [m2] */
    double air_density;       /* [kg/m3] */
    double gravity;           /* [m/s2] */
    double slope;             /* [rad] road gradient angle, uphill positive */
    double wheel_radius;      /* [m] */
    double gear_ratio;        /* [1] motor speed / wheel speed */
    double gear_efficiency;   /* [1] */
    double max_motor_torque;  /* [N.m] control-unit limit at full throttle */
    double max_brake_torque;  /* [N.m] at the wheels, full brake pedal */
    double aux_power;         /* [W] */
    double max_power;         /* [W] power-source discharge limit */
    double min_power;         /* [W] power-source charge (recuperation) limit, negative */

    /* driver */
    double throttle_P, throttle_I, brake_P, brake_I;
    double hysteresis;        /* [m/s] relay threshold on the speed error */
    double sample_period;     /* [s] */
    int cycle;                /* 1-based index into CYCLES (cycles_table.h) */

    /* discrete states */
    double held_error;        /* [m/s] speed error sampled at the last controller tick */
    long long next_sample;    /* index k of the next controller tick at k * sample_period */
    bool throttle_active;     /* relay: true = throttle PI drives, false = brake PI */
    bool standstill;          /* vehicle held at speed 0 */
    bool torque_limited;      /* demand above the full-load curve (selects indicators) */
    int load_interval;        /* full-load curve interval containing the motor speed */
} ModelData;

#endif
