/*
 * Bouncing ball physics.
 *
 *   der(h) = v,  der(v) = -g          while flying
 *   when h crosses 0 downwards:  v := -e * v   (state reset, reported to the importer)
 *
 * The rebound speeds form a geometric series, so impacts accumulate before a finite time
 * (Zeno behaviour). To stay simulatable, a rebound slower than v_min latches the ball at
 * rest on the ground: h = v = 0 and both derivatives 0 from then on.
 *
 * Analytic reference: dropped from h0 with v0 = 0, the first impact is at sqrt(2 h0 / g)
 * with speed sqrt(2 g h0); each later flight lasts 2 e^k sqrt(2 h0 / g) (k = 1, 2, ...).
 */
#include "model.h"

void model_set_start_values(ModelInstance *m) {
    m->data.h = 1.0;
    m->data.v = 0.0;
    m->data.g = 9.81;
    m->data.e = 0.7;
    m->data.v_min = 0.1;
    m->data.bounces = 0;
    m->data.at_rest = false;
}

void model_initialize(ModelInstance *m) {
    m->nextEventTimeDefined = false; /* only state events */
}

void model_event_update(ModelInstance *m) {
    ModelData *d = &m->data;
    if (d->at_rest || !(d->h <= 0.0 && d->v < 0.0)) {
        return;
    }
    d->bounces++;
    d->h = 0.0;
    d->v = -d->e * d->v;
    if (d->v < d->v_min) {
        d->v = 0.0;
        d->at_rest = true;
    }
    m->valuesOfContinuousStatesChanged = true;
    model_log(m, fmi2OK, "logEvents", "impact %d at t=%g, rebound speed %g m/s%s", d->bounces,
              m->time, d->v, d->at_rest ? " (ball at rest)" : "");
}

static double der_h(const ModelData *d) { return d->at_rest ? 0.0 : d->v; }

static double der_v(const ModelData *d) { return d->at_rest ? 0.0 : -d->g; }

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    const ModelData *d = &m->data;
    switch (vr) {
    case VR_H: *value = d->h; return fmi2OK;
    case VR_DER_H: *value = der_h(d); return fmi2OK;
    case VR_V: *value = d->v; return fmi2OK;
    case VR_DER_V: *value = der_v(d); return fmi2OK;
    case VR_G: *value = d->g; return fmi2OK;
    case VR_E: *value = d->e; return fmi2OK;
    case VR_V_MIN: *value = d->v_min; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    bool before_init = m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE);
    switch (vr) {
    case VR_H: if (!before_init) return fmi2Error; m->data.h = value; return fmi2OK;
    case VR_V: if (!before_init) return fmi2Error; m->data.v = value; return fmi2OK;
    case VR_G: if (!before_init) return fmi2Error; m->data.g = value; return fmi2OK;
    case VR_V_MIN: if (!before_init) return fmi2Error; m->data.v_min = value; return fmi2OK;
    /* e is tunable: it may change in event mode too. */
    case VR_E:
        if (!(before_init || m->state == STATE_EVENT_MODE)) return fmi2Error;
        m->data.e = value;
        return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value) {
    if (vr != VR_BOUNCES) {
        return fmi2Error;
    }
    *value = m->data.bounces;
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
    x[0] = m->data.h;
    x[1] = m->data.v;
}

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    m->data.h = x[0];
    m->data.v = x[1];
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    dx[0] = der_h(&m->data);
    dx[1] = der_v(&m->data);
}

void model_get_event_indicators(ModelInstance *m, double z[]) {
    /* At rest the indicator is held positive so the resting ball triggers no events. */
    z[0] = m->data.at_rest ? 1.0 : m->data.h;
}

/* Jacobian of (der_h, der_v, h, v) with respect to (h, v, g); zero while at rest. */
fmi2Status model_get_partial_derivative(ModelInstance *m, fmi2ValueReference unknown,
                                        fmi2ValueReference known, double *partial) {
    bool flying = !m->data.at_rest;
    if (known != VR_H && known != VR_V && known != VR_G) {
        return fmi2Error;
    }
    switch (unknown) {
    case VR_DER_H: *partial = (flying && known == VR_V) ? 1.0 : 0.0; return fmi2OK;
    case VR_DER_V: *partial = (flying && known == VR_G) ? -1.0 : 0.0; return fmi2OK;
    case VR_H: *partial = known == VR_H ? 1.0 : 0.0; return fmi2OK;
    case VR_V: *partial = known == VR_V ? 1.0 : 0.0; return fmi2OK;
    default: return fmi2Error;
    }
}
