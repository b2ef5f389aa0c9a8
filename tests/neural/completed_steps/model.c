/*
 * Completed integrator steps, observable: der(p) = 1 and p := 0 when p reaches p_max (state
 * events); der(r) = +1 until the step event, -1 after. The step event is requested by the first
 * fmi2CompletedIntegratorStep at a time >= t_step, and only by it (other events do not turn r), so
 * an importer that skips the completed-integrator-step call after the step cut at a state event
 * turns r later. `steps` counts the fmi2CompletedIntegratorStep calls.
 */
#include "model.h"

void model_set_start_values(ModelInstance *m) {
    ModelData *d = &m->data;
    d->p = 0.0;
    d->r = 0.0;
    d->p_max = 0.95;
    d->t_step = 0.93;
    d->steps = 0.0;
    d->step_event_time = -1.0;
    d->requested = false;
    d->done = false;
}

void model_initialize(ModelInstance *m) { (void)m; }

void model_event_update(ModelInstance *m) {
    ModelData *d = &m->data;
    if (d->p >= d->p_max) {
        d->p = 0.0;
        m->valuesOfContinuousStatesChanged = true;
    }
    if (d->requested && !d->done) {
        d->done = true;
        d->step_event_time = m->time;
    }
}

bool model_completed_integrator_step(ModelInstance *m) {
    ModelData *d = &m->data;
    d->steps += 1.0;
    if (!d->done && m->time >= d->t_step) {
        d->requested = true;
    }
    return d->requested && !d->done;
}

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    const ModelData *d = &m->data;
    switch (vr) {
    case VR_P: *value = d->p; return fmi2OK;
    case VR_DER_P: *value = 1.0; return fmi2OK;
    case VR_R: *value = d->r; return fmi2OK;
    case VR_DER_R: *value = d->done ? -1.0 : 1.0; return fmi2OK;
    case VR_P_MAX: *value = d->p_max; return fmi2OK;
    case VR_T_STEP: *value = d->t_step; return fmi2OK;
    case VR_STEPS: *value = d->steps; return fmi2OK;
    case VR_STEP_EVENT_TIME: *value = d->step_event_time; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    ModelData *d = &m->data;
    if (!(m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE))) {
        return fmi2Error;
    }
    switch (vr) {
    case VR_P: d->p = value; return fmi2OK;
    case VR_R: d->r = value; return fmi2OK;
    case VR_P_MAX: if (value <= 0) return fmi2Error; d->p_max = value; return fmi2OK;
    case VR_T_STEP: d->t_step = value; return fmi2OK;
    default: return fmi2Error;
    }
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
    x[0] = m->data.p;
    x[1] = m->data.r;
}

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    m->data.p = x[0];
    m->data.r = x[1];
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    dx[0] = 1.0;
    dx[1] = m->data.done ? -1.0 : 1.0;
}

void model_get_event_indicators(ModelInstance *m, double z[]) {
    z[0] = m->data.p - m->data.p_max;
}
