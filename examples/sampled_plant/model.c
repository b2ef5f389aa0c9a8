/*
 * DC motor speed control with a sampled PI controller.
 *
 * Plant (continuous):   L di/dt = u - R i - K w,     J dw/dt = K i - b w
 * Controller (discrete, at t_k = startTime + k Ts, k = 0, 1, ...):
 *     e = setpoint - w(t_k)
 *     integral += Ki Ts e                   (frozen while the output saturates: anti-windup)
 *     u = clamp(Kp e + integral, -u_max, u_max), held constant until t_{k+1}
 *
 * The integral action drives the speed to the set point: in steady state w = setpoint,
 * i = b w / K and u = R i + K w. Sample k = 0 is taken at initialization; later samples
 * are time events announced through nextEventTime.
 */
#include <math.h>

#include "model.h"

void model_set_start_values(ModelInstance *m) {
    ModelData *d = &m->data;
    d->i = 0.0;
    d->w = 0.0;
    d->R = 1.0;
    d->L = 0.05;
    d->K = 0.5;
    d->J = 0.1;
    d->b = 0.05;
    d->setpoint = 1.0;
    d->u = 0.0;
    d->integral = 0.0;
    d->Kp = 0.5;
    d->Ki = 2.0;
    d->Ts = 0.01;
    d->u_max = 24.0;
    d->samples = 0;
}

static double clamp(double value, double limit) { return fmax(-limit, fmin(limit, value)); }

static void schedule_next_sample(ModelInstance *m) {
    /* From the sample index, not by accumulating Ts, so rounding does not drift. */
    m->nextEventTimeDefined = true;
    m->nextEventTime = m->startTime + m->data.samples * m->data.Ts;
}

static void take_sample(ModelInstance *m) {
    ModelData *d = &m->data;
    double error = d->setpoint - d->w;
    double integral = d->integral + d->Ki * d->Ts * error;
    double unclamped = d->Kp * error + integral;
    d->u = clamp(unclamped, d->u_max);
    if (unclamped == d->u) {
        d->integral = integral;
    }
    d->samples++;
    schedule_next_sample(m);
}

void model_initialize(ModelInstance *m) {
    take_sample(m); /* k = 0 at the start time */
}

void model_event_update(ModelInstance *m) {
    /* Tolerate round-off in the importer's event time, relative to the sample period. */
    if (m->nextEventTimeDefined && m->time >= m->nextEventTime - 1e-9 * m->data.Ts) {
        take_sample(m);
    }
}

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    const ModelData *d = &m->data;
    double dx[NX];
    switch (vr) {
    case VR_I: *value = d->i; return fmi2OK;
    case VR_W: *value = d->w; return fmi2OK;
    case VR_DER_I: model_get_derivatives(m, dx); *value = dx[0]; return fmi2OK;
    case VR_DER_W: model_get_derivatives(m, dx); *value = dx[1]; return fmi2OK;
    case VR_SETPOINT: *value = d->setpoint; return fmi2OK;
    case VR_U: *value = d->u; return fmi2OK;
    case VR_INTEGRAL: *value = d->integral; return fmi2OK;
    case VR_R: *value = d->R; return fmi2OK;
    case VR_L: *value = d->L; return fmi2OK;
    case VR_K: *value = d->K; return fmi2OK;
    case VR_J: *value = d->J; return fmi2OK;
    case VR_B: *value = d->b; return fmi2OK;
    case VR_KP: *value = d->Kp; return fmi2OK;
    case VR_KI: *value = d->Ki; return fmi2OK;
    case VR_TS: *value = d->Ts; return fmi2OK;
    case VR_U_MAX: *value = d->u_max; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    ModelData *d = &m->data;
    bool before_init = m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE);
    bool tunable = before_init || m->state == STATE_EVENT_MODE;
    switch (vr) {
    case VR_SETPOINT: d->setpoint = value; return fmi2OK; /* continuous input: any mode */
    case VR_I: if (!before_init) return fmi2Error; d->i = value; return fmi2OK;
    case VR_W: if (!before_init) return fmi2Error; d->w = value; return fmi2OK;
    case VR_R: if (!before_init) return fmi2Error; d->R = value; return fmi2OK;
    case VR_L: if (!before_init) return fmi2Error; d->L = value; return fmi2OK;
    case VR_K: if (!before_init) return fmi2Error; d->K = value; return fmi2OK;
    case VR_J: if (!before_init) return fmi2Error; d->J = value; return fmi2OK;
    case VR_B: if (!before_init) return fmi2Error; d->b = value; return fmi2OK;
    case VR_TS: if (!before_init || value <= 0) return fmi2Error; d->Ts = value; return fmi2OK;
    case VR_KP: if (!tunable) return fmi2Error; d->Kp = value; return fmi2OK;
    case VR_KI: if (!tunable) return fmi2Error; d->Ki = value; return fmi2OK;
    case VR_U_MAX: if (!tunable) return fmi2Error; d->u_max = value; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value) {
    if (vr != VR_SAMPLES) {
        return fmi2Error;
    }
    *value = m->data.samples;
    return fmi2OK;
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
    x[0] = m->data.i;
    x[1] = m->data.w;
}

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    m->data.i = x[0];
    m->data.w = x[1];
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    const ModelData *d = &m->data;
    dx[0] = (d->u - d->R * d->i - d->K * d->w) / d->L;
    dx[1] = (d->K * d->i - d->b * d->w) / d->J;
}

void model_get_event_indicators(ModelInstance *m, double z[]) {
    (void)m, (void)z; /* NZ == 0 */
}
