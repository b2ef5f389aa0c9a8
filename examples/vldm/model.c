/*
 * VLDM physics: an electric Smart fortwo driven along a driving cycle.
 *
 *   cycle table -> target speed --(speed error)--> driver (two sampled PI controllers,
 *   selected by a hysteresis relay) -> throttle / brake pedal -> control unit and motor
 *   (torque demand, full-load curve) -> gear -> wheels -> vehicle (mass, road loads,
 *   standstill) -> speed; motor speed and torque -> loss maps -> electrical power -> energy.
 *
 * Continuous states: see config.h (X_*). Discrete states: the held speed error, the relay,
 * the standstill flag, the index of the next controller tick and two indicator selectors.
 * Sign convention: speed error = target speed - speed (positive: the car is too slow).
 *
 * Event indicators (NZ = 12), each a continuous function between events:
 *   Z_RELAY            relay threshold of the current mode: throttle mode -> error + h
 *                      (falls below 0: switch to brake), brake mode -> error - h
 *                      (rises above 0: switch to throttle). h = hysteresis = 0.05 m/s.
 *   Z_THROTTLE_LOW     throttle PI output = 0 (lower pedal saturation)
 *   Z_THROTTLE_HIGH    throttle PI output = 1 (upper pedal saturation)
 *   Z_BRAKE_LOW        brake PI output = 0
 *   Z_BRAKE_HIGH       brake PI output = 1
 *   Z_TORQUE_LIMIT     full-load torque - torque demand (the motor torque limit engages)
 *   Z_LOAD_LOWER/UPPER motor speed against the bounds of the full-load-curve interval it
 *                      lies in; only while the torque is limited (the curve's kinks then
 *                      shape the acceleration), constant 1 otherwise.
 *   Z_STOP             speed while moving (reaches 0: the car stops), constant 1 at rest
 *   Z_START            at rest: drive force - slope force - rolling resistance - brake
 *                      force (rises above 0: the car starts), constant -1 while moving
 *   Z_RECUPERATION     power demand - charge limit (-10 kW)
 *   Z_DISCHARGE        discharge limit (400 kW) - power demand
 * Not needed as indicators: the cycle table kinks lie on the 0.01 s controller grid (time
 * events); the loss-map kinks only shape the integrand of the energy; the minimum-load
 * curve is 0 and the torque demand is >= 0, so its limit coincides with Z_THROTTLE_LOW.
 */
#include <math.h>
#include <string.h>

#include "model.h"
#include "cycles_table.h"
#include "maps_table.h"

enum {
    Z_RELAY,
    Z_THROTTLE_LOW,
    Z_THROTTLE_HIGH,
    Z_BRAKE_LOW,
    Z_BRAKE_HIGH,
    Z_TORQUE_LIMIT,
    Z_LOAD_LOWER,
    Z_LOAD_UPPER,
    Z_STOP,
    Z_START,
    Z_RECUPERATION,
    Z_DISCHARGE,
    Z_COUNT
};

_Static_assert(Z_COUNT == NZ, "NZ in config.h must match the event indicator list");

/* "Truth" variants: physics the declared model lacks, switched on by compile definitions
 * only, so that their FMUs look exactly like the declared model from the outside. */
#ifdef VLDM_TRUTH_EXTRA_RESISTANCE
/* Drivetrain and tyre friction growing with speed: F = c1 * v + c2 * v * |v|. */
static const double EXTRA_DRAG_LINEAR = 1.5;     /* [N/(m/s)] */
static const double EXTRA_DRAG_QUADRATIC = 0.06; /* [N/(m/s)^2] */
#endif
#ifdef VLDM_TRUTH_EXTRA_LOSS
/* Electrical loss proportional to the mechanical motor power (e.g. battery and cabling). */
static const double EXTRA_LOSS_FRACTION = 0.10;
#endif

/* Every algebraic quantity of the model at the current time, states and discrete states. */
typedef struct {
    double target_speed, error;
    double throttle_raw, brake_raw, throttle, brake;
    double motor_speed, torque_demand, torque_limit, motor_torque, brake_torque;
    double drive_force, brake_force, rolling_force, air_force, slope_force, extra_force;
    double resistance_force, acceleration;
    double start_margin; /* drive force minus all forces able to hold the car at rest */
    double motor_power, pe_loss, extra_loss, power_demand, power;
} Signals;

/* ---------------------------------------------------------------------------------------
 * Table look-up.
 */
static double clamp(double value, double low, double high) {
    return value < low ? low : (value > high ? high : value);
}

/* Index i of the interval axis[i] <= x < axis[i+1], clamped to [0, n-2]. */
static int find_interval(const double *axis, int n, double x) {
    int low = 0, high = n - 1;
    while (high - low > 1) {
        int mid = (low + high) / 2;
        if (axis[mid] <= x) {
            low = mid;
        } else {
            high = mid;
        }
    }
    return low;
}

/* Linear interpolation holding the end values outside the axis. */
static double interpolate_1d(const double *axis, const double *values, int n, double x) {
    x = clamp(x, axis[0], axis[n - 1]);
    int i = find_interval(axis, n, x);
    double f = (x - axis[i]) / (axis[i + 1] - axis[i]);
    return values[i] + f * (values[i + 1] - values[i]);
}

/* Bilinear interpolation in a row-major map, holding the edge values outside it. */
static double interpolate_2d(const double *rows, int n_rows, const double *columns,
                             int n_columns, const double *values, double r, double c) {
    r = clamp(r, rows[0], rows[n_rows - 1]);
    c = clamp(c, columns[0], columns[n_columns - 1]);
    int i = find_interval(rows, n_rows, r);
    int j = find_interval(columns, n_columns, c);
    double fr = (r - rows[i]) / (rows[i + 1] - rows[i]);
    double fc = (c - columns[j]) / (columns[j + 1] - columns[j]);
    const double *v0 = values + (size_t)i * n_columns;
    const double *v1 = v0 + n_columns;
    double low = v0[j] + fc * (v0[j + 1] - v0[j]);
    double high = v1[j] + fc * (v1[j + 1] - v1[j]);
    return low + fr * (high - low);
}

/* Target speed of a cycle: linear between samples, the first value before the cycle
 * starts and 0 after it ends. */
static double cycle_speed(int cycle, double t) {
    const CycleTable *table = &CYCLES[cycle - 1];
    double u = (t - table->start_time) / table->step;
    int last = table->length - 1;
    if (u <= 0.0) {
        return table->speed[0];
    }
    if (u > last) {
        return 0.0;
    }
    int i = (int)u;
    if (i >= last) {
        return table->speed[last];
    }
    return table->speed[i] + (u - i) * (table->speed[i + 1] - table->speed[i]);
}

/* ---------------------------------------------------------------------------------------
 * Physics.
 */
static void compute_driver(const ModelInstance *m, Signals *s) {
    const ModelData *d = &m->data;
    s->target_speed = cycle_speed(d->cycle, m->time);
    s->error = s->target_speed - d->x[X_SPEED];
    /* Both PI controllers act on the error held since the last tick; the brake PI sees
     * the negated error so that a positive output means "brake harder". */
    s->throttle_raw = d->throttle_P * d->held_error + d->x[X_THROTTLE_INTEGRATOR];
    s->brake_raw = -d->brake_P * d->held_error + d->x[X_BRAKE_INTEGRATOR];
    s->throttle = d->throttle_active ? clamp(s->throttle_raw, 0.0, 1.0) : 0.0;
    s->brake = d->throttle_active ? 0.0 : clamp(s->brake_raw, 0.0, 1.0);
}

static void compute_drivetrain(const ModelInstance *m, Signals *s) {
    const ModelData *d = &m->data;
    s->motor_speed = d->x[X_SPEED] * d->gear_ratio / d->wheel_radius;
    s->torque_demand = s->throttle * d->max_motor_torque;
    s->torque_limit =
        interpolate_1d(FULL_LOAD_OMEGA, FULL_LOAD_TORQUE, FULL_LOAD_LENGTH, s->motor_speed);
    double torque_floor =
        interpolate_1d(MIN_LOAD_OMEGA, MIN_LOAD_TORQUE, MIN_LOAD_LENGTH, s->motor_speed);
    s->motor_torque = fmin(fmax(s->torque_demand, torque_floor), s->torque_limit);
    s->brake_torque = s->brake * d->max_brake_torque;
    double efficiency = s->motor_torque >= 0.0 ? d->gear_efficiency : 1.0 / d->gear_efficiency;
    s->drive_force = s->motor_torque * d->gear_ratio * efficiency / d->wheel_radius;
}

static void compute_vehicle(const ModelInstance *m, Signals *s) {
    const ModelData *d = &m->data;
    double v = d->x[X_SPEED];
    double weight = d->mass * d->gravity;
    double rolling = d->rolling_coefficient * weight * cos(d->slope);
    double brake = s->brake_torque / d->wheel_radius;
    s->slope_force = weight * sin(d->slope);
    s->air_force = 0.5 * d->air_density * d->drag_coefficient * d->frontal_area * v * fabs(v);
#ifdef VLDM_TRUTH_EXTRA_RESISTANCE
    s->extra_force = EXTRA_DRAG_LINEAR * v + EXTRA_DRAG_QUADRATIC * v * fabs(v);
#else
    s->extra_force = 0.0;
#endif
    s->start_margin = s->drive_force - s->slope_force - rolling - brake;
    if (d->standstill) {
        /* Held at rest: rolling resistance and brake act as static friction and take up
         * only what the drive force pushes (the car cannot roll backwards either). */
        double push = s->drive_force - s->slope_force;
        s->rolling_force = clamp(push, 0.0, rolling);
        s->brake_force = clamp(push - s->rolling_force, 0.0, brake);
        s->acceleration = 0.0;
    } else {
        s->rolling_force = rolling;
        s->brake_force = brake;
    }
    s->resistance_force = s->rolling_force + s->air_force + s->slope_force + s->extra_force;
    if (!d->standstill) {
        s->acceleration = (s->drive_force - s->brake_force - s->resistance_force) /
                          (d->mass * d->mass_factor);
    }
}

static void compute_power(const ModelInstance *m, Signals *s) {
    const ModelData *d = &m->data;
    s->motor_power = interpolate_2d(MOTOR_POWER_OMEGA, MOTOR_POWER_ROWS, MOTOR_POWER_TORQUE,
                                    MOTOR_POWER_COLUMNS, MOTOR_POWER_VALUES, s->motor_speed,
                                    s->motor_torque);
    s->pe_loss = interpolate_2d(PE_LOSS_OMEGA, PE_LOSS_ROWS, PE_LOSS_TORQUE, PE_LOSS_COLUMNS,
                                PE_LOSS_VALUES, s->motor_speed, fabs(s->motor_torque));
#ifdef VLDM_TRUTH_EXTRA_LOSS
    s->extra_loss = EXTRA_LOSS_FRACTION * fabs(s->motor_torque * s->motor_speed);
#else
    s->extra_loss = 0.0;
#endif
    s->power_demand = s->motor_power + s->pe_loss + d->aux_power + s->extra_loss;
    s->power = clamp(s->power_demand, d->min_power, d->max_power);
}

static void compute(const ModelInstance *m, Signals *s) {
    memset(s, 0, sizeof(*s));
    compute_driver(m, s);
    compute_drivetrain(m, s);
    compute_vehicle(m, s);
    compute_power(m, s);
}

/* ---------------------------------------------------------------------------------------
 * Discrete behaviour: controller ticks, relay, standstill.
 */
static double tick_time(const ModelData *d, long long k) { return (double)k * d->sample_period; }

/* Samples the speed error and schedules the next tick (ticks at k * sample_period). */
static void sample_error(ModelInstance *m) {
    ModelData *d = &m->data;
    Signals s;
    compute(m, &s);
    d->held_error = s.error;
    d->next_sample = (long long)floor(m->time / d->sample_period + 0.5) + 1;
    if (tick_time(d, d->next_sample) <= m->time) {
        d->next_sample++;
    }
}

static bool tick_due(const ModelInstance *m) {
    const ModelData *d = &m->data;
    double t_tick = tick_time(d, d->next_sample);
    return m->time >= t_tick - 1e-9 * fmax(1.0, fabs(t_tick));
}

/* Hysteresis relay choosing the active PI controller; the newly activated integrator
 * restarts from 0 (rising edge of its activation). Returns true if it switched. */
static bool update_relay(ModelInstance *m, const Signals *s) {
    ModelData *d = &m->data;
    if (!d->throttle_active && s->error > d->hysteresis) {
        d->throttle_active = true;
        d->x[X_THROTTLE_INTEGRATOR] = 0.0;
    } else if (d->throttle_active && s->error < -d->hysteresis) {
        d->throttle_active = false;
        d->x[X_BRAKE_INTEGRATOR] = 0.0;
    } else {
        return false;
    }
    m->valuesOfContinuousStatesChanged = true;
    return true;
}

/* Stops the car when its speed reaches 0 unless the drive force can keep it going, and
 * releases it once the drive force exceeds everything that holds it. Returns true if
 * the standstill flag changed. */
static bool update_standstill(ModelInstance *m, const Signals *s) {
    ModelData *d = &m->data;
    if (!d->standstill && d->x[X_SPEED] <= 0.0) {
        if (d->x[X_SPEED] < 0.0) {
            d->x[X_SPEED] = 0.0; /* the solver overshot the stop */
            m->valuesOfContinuousStatesChanged = true;
        }
        d->standstill = s->start_margin <= 0.0;
        return d->standstill;
    }
    if (d->standstill && s->start_margin > 0.0) {
        d->standstill = false;
        return true;
    }
    return false;
}

/* Selects which full-load-curve interval the indicators watch (see Z_LOAD_*). */
static void update_indicator_selectors(ModelInstance *m, const Signals *s) {
    ModelData *d = &m->data;
    d->torque_limited = s->torque_demand > s->torque_limit;
    d->load_interval = find_interval(FULL_LOAD_OMEGA, FULL_LOAD_LENGTH, s->motor_speed);
}

/* Relay and standstill depend on each other through the pedals: iterate to a fixed point
 * (a relay switch happens at most once per event, so this ends after a few passes). */
static void update_modes(ModelInstance *m) {
    Signals s;
    for (int pass = 0; pass < 4; pass++) {
        compute(m, &s);
        bool relay_switched = update_relay(m, &s);
        if (relay_switched) {
            compute(m, &s);
        }
        if (!update_standstill(m, &s) && !relay_switched) {
            break;
        }
    }
    compute(m, &s);
    update_indicator_selectors(m, &s);
}

static void schedule_next_tick(ModelInstance *m) {
    m->nextEventTimeDefined = true;
    m->nextEventTime = tick_time(&m->data, m->data.next_sample);
}

/* ---------------------------------------------------------------------------------------
 * model.h interface.
 */
void model_set_start_values(ModelInstance *m) {
    ModelData *d = &m->data;
    memset(d->x, 0, sizeof(d->x));
    d->mass = 988.5;
    d->mass_factor = 1.022;
    d->rolling_coefficient = 0.0185;
    d->drag_coefficient = 0.37;
    d->frontal_area = 1.947;
    d->air_density = 1.2041;
    d->gravity = 9.8;
    d->slope = 0.0;
    d->wheel_radius = 0.277;
    d->gear_ratio = 5.697;
    d->gear_efficiency = 1.0;
    d->max_motor_torque = 110.0;
    d->max_brake_torque = 448.0;
    d->aux_power = 142.6;
    d->max_power = 400e3;
    d->min_power = -10e3;
    d->throttle_P = 7.0;
    d->throttle_I = 1.0;
    d->brake_P = 7.0;
    d->brake_I = 1.5;
    d->hysteresis = 0.05;
    d->sample_period = 0.01;
    d->cycle = 1;
    d->held_error = 0.0;
    d->next_sample = 0;
    d->throttle_active = false; /* the car waits on the brake */
    d->standstill = true;
    d->torque_limited = false;
    d->load_interval = 0;
}

void model_initialize(ModelInstance *m) {
    ModelData *d = &m->data;
    if (d->x[X_SPEED] < 0.0) {
        d->x[X_SPEED] = 0.0; /* the model has no reverse driving */
    }
    d->standstill = d->x[X_SPEED] <= 0.0;
    sample_error(m);
    /* The relay starts in the mode the initial error asks for; that is no rising edge, so
     * the integrators keep their start values. */
    d->throttle_active = d->held_error > d->hysteresis;
    update_modes(m);
    schedule_next_tick(m);
}

void model_event_update(ModelInstance *m) {
    if (tick_due(m)) {
        sample_error(m);
    }
    update_modes(m);
    schedule_next_tick(m);
}

void model_get_continuous_states(const ModelInstance *m, double x[]) {
    memcpy(x, m->data.x, sizeof(m->data.x));
}

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    memcpy(m->data.x, x, sizeof(m->data.x));
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    const ModelData *d = &m->data;
    Signals s;
    compute(m, &s);
    /* The active integrator integrates the held error (no anti-windup); the other rests. */
    dx[X_THROTTLE_INTEGRATOR] = d->throttle_active ? d->throttle_I * d->held_error : 0.0;
    dx[X_BRAKE_INTEGRATOR] = d->throttle_active ? 0.0 : -d->brake_I * d->held_error;
    dx[X_CYCLE_POSITION] = s.target_speed;
    dx[X_POSITION] = d->x[X_SPEED];
    dx[X_SPEED] = s.acceleration;
    dx[X_ENERGY] = s.power;
}

void model_get_event_indicators(ModelInstance *m, double z[]) {
    const ModelData *d = &m->data;
    Signals s;
    compute(m, &s);
    z[Z_RELAY] = d->throttle_active ? s.error + d->hysteresis : s.error - d->hysteresis;
    z[Z_THROTTLE_LOW] = s.throttle_raw;
    z[Z_THROTTLE_HIGH] = s.throttle_raw - 1.0;
    z[Z_BRAKE_LOW] = s.brake_raw;
    z[Z_BRAKE_HIGH] = s.brake_raw - 1.0;
    z[Z_TORQUE_LIMIT] = s.torque_limit - s.torque_demand;
    if (d->torque_limited) {
        z[Z_LOAD_LOWER] = s.motor_speed - FULL_LOAD_OMEGA[d->load_interval];
        z[Z_LOAD_UPPER] = FULL_LOAD_OMEGA[d->load_interval + 1] - s.motor_speed;
    } else {
        z[Z_LOAD_LOWER] = 1.0;
        z[Z_LOAD_UPPER] = 1.0;
    }
    z[Z_STOP] = d->standstill ? 1.0 : d->x[X_SPEED];
    z[Z_START] = d->standstill ? s.start_margin : -1.0;
    z[Z_RECUPERATION] = s.power_demand - d->min_power;
    z[Z_DISCHARGE] = d->max_power - s.power_demand;
}

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    const ModelData *d = &m->data;
    if (vr < NX) {
        *value = d->x[vr];
        return fmi2OK;
    }
    if (vr < 2 * NX) {
        double dx[NX];
        model_get_derivatives(m, dx);
        *value = dx[vr - NX];
        return fmi2OK;
    }
    Signals s;
    compute(m, &s);
    switch (vr) {
    case VR_ACCELERATION: *value = s.acceleration; return fmi2OK;
    case VR_POWER: *value = s.power; return fmi2OK;
    case VR_TARGET_SPEED: *value = s.target_speed; return fmi2OK;
    case VR_SPEED_ERROR: *value = s.error; return fmi2OK;
    case VR_HELD_ERROR: *value = d->held_error; return fmi2OK;
    case VR_THROTTLE: *value = s.throttle; return fmi2OK;
    case VR_BRAKE: *value = s.brake; return fmi2OK;
    case VR_MOTOR_SPEED: *value = s.motor_speed; return fmi2OK;
    case VR_MOTOR_TORQUE_DEMAND: *value = s.torque_demand; return fmi2OK;
    case VR_MOTOR_TORQUE_LIMIT: *value = s.torque_limit; return fmi2OK;
    case VR_MOTOR_TORQUE: *value = s.motor_torque; return fmi2OK;
    case VR_BRAKE_TORQUE: *value = s.brake_torque; return fmi2OK;
    case VR_DRIVE_FORCE: *value = s.drive_force; return fmi2OK;
    case VR_BRAKE_FORCE: *value = s.brake_force; return fmi2OK;
    case VR_ROLLING_RESISTANCE_FORCE: *value = s.rolling_force; return fmi2OK;
    case VR_AIR_RESISTANCE_FORCE: *value = s.air_force; return fmi2OK;
    case VR_SLOPE_FORCE: *value = s.slope_force; return fmi2OK;
    case VR_RESISTANCE_FORCE: *value = s.resistance_force; return fmi2OK;
    case VR_MOTOR_POWER: *value = s.motor_power; return fmi2OK;
    case VR_POWER_ELECTRONICS_LOSS: *value = s.pe_loss; return fmi2OK;
    case VR_POWER_DEMAND: *value = s.power_demand; return fmi2OK;
    case VR_MASS: *value = d->mass; return fmi2OK;
    case VR_MASS_FACTOR: *value = d->mass_factor; return fmi2OK;
    case VR_ROLLING_COEFFICIENT: *value = d->rolling_coefficient; return fmi2OK;
    case VR_DRAG_COEFFICIENT: *value = d->drag_coefficient; return fmi2OK;
    case VR_FRONTAL_AREA: *value = d->frontal_area; return fmi2OK;
    case VR_AIR_DENSITY: *value = d->air_density; return fmi2OK;
    case VR_GRAVITY: *value = d->gravity; return fmi2OK;
    case VR_SLOPE: *value = d->slope; return fmi2OK;
    case VR_WHEEL_RADIUS: *value = d->wheel_radius; return fmi2OK;
    case VR_GEAR_RATIO: *value = d->gear_ratio; return fmi2OK;
    case VR_GEAR_EFFICIENCY: *value = d->gear_efficiency; return fmi2OK;
    case VR_MAX_MOTOR_TORQUE: *value = d->max_motor_torque; return fmi2OK;
    case VR_MAX_BRAKE_TORQUE: *value = d->max_brake_torque; return fmi2OK;
    case VR_AUX_POWER: *value = d->aux_power; return fmi2OK;
    case VR_MAX_POWER: *value = d->max_power; return fmi2OK;
    case VR_MIN_POWER: *value = d->min_power; return fmi2OK;
    case VR_THROTTLE_P: *value = d->throttle_P; return fmi2OK;
    case VR_THROTTLE_I: *value = d->throttle_I; return fmi2OK;
    case VR_BRAKE_P: *value = d->brake_P; return fmi2OK;
    case VR_BRAKE_I: *value = d->brake_I; return fmi2OK;
    case VR_HYSTERESIS: *value = d->hysteresis; return fmi2OK;
    case VR_SAMPLE_PERIOD: *value = d->sample_period; return fmi2OK;
    default: return fmi2Error;
    }
}

/* Where a parameter lives, so that one setter handles them all. */
static double *parameter_slot(ModelData *d, fmi2ValueReference vr) {
    switch (vr) {
    case VR_MASS: return &d->mass;
    case VR_MASS_FACTOR: return &d->mass_factor;
    case VR_ROLLING_COEFFICIENT: return &d->rolling_coefficient;
    case VR_DRAG_COEFFICIENT: return &d->drag_coefficient;
    case VR_FRONTAL_AREA: return &d->frontal_area;
    case VR_AIR_DENSITY: return &d->air_density;
    case VR_GRAVITY: return &d->gravity;
    case VR_SLOPE: return &d->slope;
    case VR_WHEEL_RADIUS: return &d->wheel_radius;
    case VR_GEAR_RATIO: return &d->gear_ratio;
    case VR_GEAR_EFFICIENCY: return &d->gear_efficiency;
    case VR_MAX_MOTOR_TORQUE: return &d->max_motor_torque;
    case VR_MAX_BRAKE_TORQUE: return &d->max_brake_torque;
    case VR_AUX_POWER: return &d->aux_power;
    case VR_MAX_POWER: return &d->max_power;
    case VR_MIN_POWER: return &d->min_power;
    case VR_THROTTLE_P: return &d->throttle_P;
    case VR_THROTTLE_I: return &d->throttle_I;
    case VR_BRAKE_P: return &d->brake_P;
    case VR_BRAKE_I: return &d->brake_I;
    case VR_HYSTERESIS: return &d->hysteresis;
    case VR_SAMPLE_PERIOD: return &d->sample_period;
    default: return NULL;
    }
}

/* Parameters that divide or scale the dynamics must be positive. */
static bool must_be_positive(fmi2ValueReference vr) {
    return vr == VR_MASS || vr == VR_MASS_FACTOR || vr == VR_WHEEL_RADIUS ||
           vr == VR_GEAR_RATIO || vr == VR_GEAR_EFFICIENCY || vr == VR_SAMPLE_PERIOD;
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    ModelData *d = &m->data;
    bool before_start = m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE);
    if (vr < NX) {
        /* Start values of the states; afterwards states change via SetContinuousStates. */
        if (!before_start) {
            return fmi2Error;
        }
        d->x[vr] = value;
        return fmi2OK;
    }
    double *slot = parameter_slot(d, vr);
    if (slot == NULL) {
        return fmi2Error;
    }
    /* The sample period is fixed; all other parameters are tunable in event mode. */
    bool allowed = before_start || (vr != VR_SAMPLE_PERIOD && (m->state & STATE_EVENT_MODE));
    if (!allowed) {
        return fmi2Error;
    }
    if (!isfinite(value) || (must_be_positive(vr) && value <= 0.0)) {
        model_log(m, fmi2Error, "logStatusError",
                  "Parameter vr=%u must be a finite%s number, got %g.", vr,
                  must_be_positive(vr) ? " positive" : "", value);
        return fmi2Error;
    }
    *slot = value;
    return fmi2OK;
}

fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value) {
    if (vr != VR_CYCLE) {
        return fmi2Error;
    }
    *value = m->data.cycle;
    return fmi2OK;
}

fmi2Status model_set_integer(ModelInstance *m, fmi2ValueReference vr, int value) {
    if (vr != VR_CYCLE || !(m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE))) {
        return fmi2Error;
    }
    if (value < 1 || value > N_CYCLES) {
        model_log(m, fmi2Error, "logStatusError",
                  "Parameter cycle must be between 1 and %d, got %d.", N_CYCLES, value);
        return fmi2Error;
    }
    m->data.cycle = value;
    return fmi2OK;
}

fmi2Status model_get_boolean(ModelInstance *m, fmi2ValueReference vr, bool *value) {
    switch (vr) {
    case VR_THROTTLE_ACTIVE: *value = m->data.throttle_active; return fmi2OK;
    case VR_BRAKE_ACTIVE: *value = !m->data.throttle_active; return fmi2OK;
    case VR_STANDSTILL: *value = m->data.standstill; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_boolean(ModelInstance *m, fmi2ValueReference vr, bool value) {
    (void)m;
    (void)vr;
    (void)value;
    return fmi2Error; /* no Boolean parameters or inputs */
}
