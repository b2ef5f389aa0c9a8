/*
 * DC drive physics: a permanent-magnet DC motor whose speed is held on a set-point profile by
 * a continuous PI controller acting on the armature voltage, against a load-torque profile.
 *
 *   speed_error   = speed_reference(t) - speed
 *   voltage       = speed_gain * speed_error + integral_gain * speed_error_integral
 *   resistance    = nominal_resistance * (1 + temperature_coefficient * (temperature - reference_temperature))
 *   der(current)  = (voltage - resistance * current - motor_constant * speed) / inductance
 *   der(speed)    = (motor_constant * current - viscous_friction * speed - load_torque(t)) / inertia
 *   der(speed_error_integral) = speed_error
 *   der(temperature) = (resistance * current^2 - (temperature - ambient_temperature) / thermal_resistance)
 *                      / heat_capacity
 *   der(energy)   = power = voltage * current      (electrical energy drawn from the supply)
 *
 * The profile (below) is a table of breakpoints: the set-point is linear between them, the load
 * torque holds its value from one breakpoint to the next. The breakpoints are time events, so
 * an integrator never steps across a kink of the set-point or a step of the load.
 *
 * "Truth" variants add physics the declared model lacks, switched on only by compile
 * definitions so that their FMUs look exactly like the declared model from the outside:
 *   DC_DRIVE_TRUTH_WINDAGE        fan and air friction torque WINDAGE * speed * |speed|,
 *                                 entering der(speed);
 *   DC_DRIVE_TRUTH_EXTRA_HEATING  heat EXTRA_HEATING_RESISTANCE * current^2 from losses the
 *                                 electrical model does not see (brushes, eddy currents),
 *                                 entering der(temperature) only.
 * and effects that no power law of one variable describes:
 *   DC_DRIVE_TRUTH_STRIBECK       Stribeck friction: a breakaway torque that is largest at low
 *                                 speed and fades out at high speed (non-monotone in speed),
 *                                 STRIBECK_TORQUE * tanh(speed / SMOOTHING) * exp(-(speed / STRIBECK_SPEED)^2),
 *                                 entering der(speed);
 *   DC_DRIVE_TRUTH_COULOMB        Coulomb friction, a sign of the speed smoothed over a narrow band,
 *                                 COULOMB_TORQUE * tanh(speed / SMOOTHING), entering der(speed);
 *   DC_DRIVE_TRUTH_SPEED_CURRENT_LOSS  an electrical loss drawn from the supply that grows with
 *                                 speed and current together (eddy currents of the commutation),
 *                                 SPEED_CURRENT_LOSS * |speed * current|, entering der(energy) and
 *                                 the power output equal to it.
 * Definitions combine: STRIBECK and SPEED_CURRENT_LOSS together put two effects into two
 * derivatives at once.
 *
 * The parameter profile_repeats drives the profile that many times in a row (1: once, then the
 * last breakpoint holds), so that a long run revisits the operating points of its start.
 */
#include <math.h>

#include "model.h"

#ifdef DC_DRIVE_TRUTH_WINDAGE
static const double WINDAGE = 3e-6; /* [N.m.s2/rad2] */
#endif
#ifdef DC_DRIVE_TRUTH_EXTRA_HEATING
static const double EXTRA_HEATING_RESISTANCE = 0.3; /* [Ohm] */
#endif
#if defined(DC_DRIVE_TRUTH_STRIBECK) || defined(DC_DRIVE_TRUTH_COULOMB)
static const double SMOOTHING = 1.0;         /* [rad/s] width of the sign's smooth step */
#endif
#ifdef DC_DRIVE_TRUTH_STRIBECK
static const double STRIBECK_TORQUE = 0.08;  /* [N.m] breakaway torque */
static const double STRIBECK_SPEED = 40.0;   /* [rad/s] speed over which it fades out */
#endif
#ifdef DC_DRIVE_TRUTH_COULOMB
static const double COULOMB_TORQUE = 0.05;   /* [N.m] */
#endif
#ifdef DC_DRIVE_TRUTH_SPEED_CURRENT_LOSS
static const double SPEED_CURRENT_LOSS = 0.01; /* [W.s/(rad.A)] */
#endif

/* Set-point and load profile: start-up, load steps, reversal, stop, high-speed run. */
static const double PROFILE_TIME[] = {0.0,  0.5,  2.5,  5.0,  7.0,   8.5,   10.0,  12.0,
                                      14.5, 17.0, 19.0, 20.5, 22.0,  22.5,  25.0,  27.0,
                                      28.0, 30.0};
static const double PROFILE_SPEED[] = {0.0,    0.0,    150.0,  150.0, 150.0, 60.0,
                                       60.0,   60.0,   -120.0, -120.0, -120.0, 0.0,
                                       0.0,    0.0,    200.0,  200.0, 200.0, 0.0};
/* Load torque [N.m] held on [PROFILE_TIME[i], PROFILE_TIME[i + 1]): steps independent of the
 * set-point ramps, so that current, acceleration and speed do not move in lockstep. */
static const double PROFILE_LOAD[] = {0.1,  0.1,  0.1,  0.5,  0.5,  0.5, 0.2, 0.2,  0.2,
                                      -0.4, -0.4, -0.4, 0.1, 0.1, 0.1, 0.4, 0.4, 0.0};
#define PROFILE_POINTS ((int)(sizeof(PROFILE_TIME) / sizeof(PROFILE_TIME[0])))

_Static_assert(sizeof(PROFILE_SPEED) == sizeof(PROFILE_TIME), "one set-point per breakpoint");
_Static_assert(sizeof(PROFILE_LOAD) == sizeof(PROFILE_TIME), "one load torque per breakpoint");

/* Every algebraic quantity of the model at the current time and states. */
typedef struct {
    double speed_reference, load_torque, speed_error, voltage, resistance;
    double motor_torque, friction_torque, copper_loss, cooling_power, extra_heat, power;
} Signals;

/* ---------------------------------------------------------------------------------------
 * Profile
 */

#define PROFILE_PERIOD (PROFILE_TIME[PROFILE_POINTS - 1])

/* The pass through the profile holding time t: 0 for the first, at most repeats - 1. */
static int pass_at(const ModelData *d, double t) {
    int last = d->profile_repeats > 1.0 ? (int)d->profile_repeats - 1 : 0;
    int pass = t > 0.0 ? (int)floor(t / PROFILE_PERIOD) : 0;
    return pass < last ? pass : last;
}

/* The segment holding time t within its pass: the last breakpoint at or before t (0 before the
 * table). */
static int segment_at(const ModelData *d, double t) {
    double local = t - d->pass * PROFILE_PERIOD;
    int i = 0;
    while (i + 1 < PROFILE_POINTS && PROFILE_TIME[i + 1] <= local) {
        i++;
    }
    return i;
}

/* Set-point in segment i, linear in time; held after the last breakpoint. The segment is the
 * discrete state, so a solver probing slightly past a breakpoint stays on the same line. */
static double speed_reference(int i, double t) {
    if (i + 1 >= PROFILE_POINTS) {
        return PROFILE_SPEED[PROFILE_POINTS - 1];
    }
    double f = (t - PROFILE_TIME[i]) / (PROFILE_TIME[i + 1] - PROFILE_TIME[i]);
    return PROFILE_SPEED[i] + f * (PROFILE_SPEED[i + 1] - PROFILE_SPEED[i]);
}

static void schedule_next_breakpoint(ModelInstance *m) {
    const ModelData *d = &m->data;
    int next = d->segment + 1;
    int last_pass = d->pass + 1 >= (int)d->profile_repeats;
    m->nextEventTimeDefined = next < PROFILE_POINTS || !last_pass;
    if (next < PROFILE_POINTS) {
        m->nextEventTime = d->pass * PROFILE_PERIOD + PROFILE_TIME[next];
    } else if (!last_pass) {  /* the next pass starts: its first breakpoint */
        m->nextEventTime = (d->pass + 1) * PROFILE_PERIOD + PROFILE_TIME[1];
    }
}

/* ---------------------------------------------------------------------------------------
 * Physics
 */

static void compute(const ModelInstance *m, Signals *s) {
    const ModelData *d = &m->data;
    double current = d->x[X_CURRENT], speed = d->x[X_SPEED];
    double temperature = d->x[X_TEMPERATURE];

    s->speed_reference = speed_reference(d->segment, m->time - d->pass * PROFILE_PERIOD);
    s->load_torque = PROFILE_LOAD[d->segment];
    s->speed_error = s->speed_reference - speed;
    s->voltage = d->speed_gain * s->speed_error + d->integral_gain * d->x[X_ERROR_INTEGRAL];
    s->resistance = d->nominal_resistance *
                    (1.0 + d->temperature_coefficient * (temperature - d->reference_temperature));
    s->motor_torque = d->motor_constant * current;
    s->friction_torque = d->viscous_friction * speed;
#ifdef DC_DRIVE_TRUTH_WINDAGE
    s->friction_torque += WINDAGE * speed * fabs(speed);
#endif
#ifdef DC_DRIVE_TRUTH_STRIBECK
    s->friction_torque += STRIBECK_TORQUE * tanh(speed / SMOOTHING) *
                          exp(-(speed / STRIBECK_SPEED) * (speed / STRIBECK_SPEED));
#endif
#ifdef DC_DRIVE_TRUTH_COULOMB
    s->friction_torque += COULOMB_TORQUE * tanh(speed / SMOOTHING);
#endif
    s->copper_loss = s->resistance * current * current;
    s->cooling_power = (temperature - d->ambient_temperature) / d->thermal_resistance;
    s->extra_heat = 0.0;
#ifdef DC_DRIVE_TRUTH_EXTRA_HEATING
    s->extra_heat = EXTRA_HEATING_RESISTANCE * current * current;
#endif
    s->power = s->voltage * current;
#ifdef DC_DRIVE_TRUTH_SPEED_CURRENT_LOSS
    s->power += SPEED_CURRENT_LOSS * fabs(speed * current);
#endif
}

static void derivatives(const ModelInstance *m, const Signals *s, double dx[NX]) {
    const ModelData *d = &m->data;
    double current = d->x[X_CURRENT], speed = d->x[X_SPEED];
    dx[X_CURRENT] =
        (s->voltage - s->resistance * current - d->motor_constant * speed) / d->inductance;
    dx[X_SPEED] = (s->motor_torque - s->friction_torque - s->load_torque) / d->inertia;
    dx[X_ERROR_INTEGRAL] = s->speed_error;
    dx[X_TEMPERATURE] = (s->copper_loss + s->extra_heat - s->cooling_power) / d->heat_capacity;
    dx[X_ENERGY] = s->power;
}

/* ---------------------------------------------------------------------------------------
 * model.h interface
 */

void model_set_start_values(ModelInstance *m) {
    ModelData *d = &m->data;
    d->x[X_CURRENT] = 0.0;
    d->x[X_SPEED] = 0.0;
    d->x[X_ERROR_INTEGRAL] = 0.0;
    d->x[X_TEMPERATURE] = 293.15;
    d->x[X_ENERGY] = 0.0;
    d->nominal_resistance = 1.2;
    d->temperature_coefficient = 0.00393;
    d->reference_temperature = 293.15;
    d->inductance = 0.01;
    d->motor_constant = 0.1;
    d->inertia = 0.01;
    d->viscous_friction = 1e-3;
    d->heat_capacity = 10.0;
    d->thermal_resistance = 2.5;
    d->ambient_temperature = 293.15;
    d->speed_gain = 2.0;
    d->integral_gain = 10.0;
    d->profile_repeats = 1.0;
    d->segment = 0;
    d->pass = 0;
}

void model_initialize(ModelInstance *m) {
    m->data.pass = pass_at(&m->data, m->time);
    m->data.segment = segment_at(&m->data, m->time);
    schedule_next_breakpoint(m);
}

void model_event_update(ModelInstance *m) {
    int pass = pass_at(&m->data, m->time);
    m->data.pass = pass;
    int segment = segment_at(&m->data, m->time);
    if (segment != m->data.segment) {
        m->data.segment = segment;
        model_log(m, fmi2OK, "logEvents", "t=%g: profile segment %d, load torque %g N.m", m->time,
                  segment, PROFILE_LOAD[segment]);
    }
    schedule_next_breakpoint(m);
}

static double *parameter(ModelData *d, fmi2ValueReference vr) {
    switch (vr) {
    case VR_NOMINAL_RESISTANCE: return &d->nominal_resistance;
    case VR_TEMPERATURE_COEFFICIENT: return &d->temperature_coefficient;
    case VR_REFERENCE_TEMPERATURE: return &d->reference_temperature;
    case VR_INDUCTANCE: return &d->inductance;
    case VR_MOTOR_CONSTANT: return &d->motor_constant;
    case VR_INERTIA: return &d->inertia;
    case VR_VISCOUS_FRICTION: return &d->viscous_friction;
    case VR_HEAT_CAPACITY: return &d->heat_capacity;
    case VR_THERMAL_RESISTANCE: return &d->thermal_resistance;
    case VR_AMBIENT_TEMPERATURE: return &d->ambient_temperature;
    case VR_SPEED_GAIN: return &d->speed_gain;
    case VR_INTEGRAL_GAIN: return &d->integral_gain;
    case VR_PROFILE_REPEATS: return &d->profile_repeats;
    default: return NULL;
    }
}

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    if (vr < NX) {
        *value = m->data.x[vr];
        return fmi2OK;
    }
    double *p = parameter(&m->data, vr);
    if (p != NULL) {
        *value = *p;
        return fmi2OK;
    }
    Signals s;
    double dx[NX];
    compute(m, &s);
    if (vr >= VR_DER_CURRENT && vr <= VR_DER_ENERGY) {
        derivatives(m, &s, dx);
        *value = dx[vr - VR_DER_CURRENT];
        return fmi2OK;
    }
    switch (vr) {
    case VR_VOLTAGE: *value = s.voltage; return fmi2OK;
    case VR_POWER: *value = s.power; return fmi2OK;
    case VR_SPEED_REFERENCE: *value = s.speed_reference; return fmi2OK;
    case VR_LOAD_TORQUE: *value = s.load_torque; return fmi2OK;
    case VR_SPEED_ERROR: *value = s.speed_error; return fmi2OK;
    case VR_MOTOR_TORQUE: *value = s.motor_torque; return fmi2OK;
    case VR_FRICTION_TORQUE: *value = s.friction_torque; return fmi2OK;
    case VR_RESISTANCE: *value = s.resistance; return fmi2OK;
    case VR_COPPER_LOSS: *value = s.copper_loss; return fmi2OK;
    case VR_COOLING_POWER: *value = s.cooling_power; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    /* States (start values) and parameters are fixed: settable before initialization ends. */
    if (!(m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE))) {
        return fmi2Error;
    }
    if (vr < NX) {
        m->data.x[vr] = value;
        return fmi2OK;
    }
    double *p = parameter(&m->data, vr);
    if (p == NULL) {
        return fmi2Error;
    }
    *p = value;
    return fmi2OK;
}

fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value) {
    (void)m, (void)vr, (void)value;
    return fmi2Error;
}

fmi2Status model_set_integer(ModelInstance *m, fmi2ValueReference vr, int value) {
    (void)m, (void)vr, (void)value;
    return fmi2Error;
}

fmi2Status model_get_boolean(ModelInstance *m, fmi2ValueReference vr, bool *value) {
    (void)m, (void)vr, (void)value;
    return fmi2Error;
}

fmi2Status model_set_boolean(ModelInstance *m, fmi2ValueReference vr, bool value) {
    (void)m, (void)vr, (void)value;
    return fmi2Error;
}

void model_get_continuous_states(const ModelInstance *m, double x[]) {
    for (int i = 0; i < NX; i++) {
        x[i] = m->data.x[i];
    }
}

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    for (int i = 0; i < NX; i++) {
        m->data.x[i] = x[i];
    }
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    Signals s;
    compute(m, &s);
    derivatives(m, &s, dx);
}

void model_get_event_indicators(ModelInstance *m, double z[]) {
    (void)m, (void)z; /* NZ = 0: never called with a non-empty array */
}
