/*
 * A model without continuous states (a stair, like the Reference FMUs' Stair): the output steps
 * up by one at every time event t = startTime + k * period. Test FMU for importers, which must not
 * call the state functions with nx = 0 on FMUs that reject such calls (built with
 * REJECT_EMPTY_ARRAYS, see fmi2_glue.c).
 */
#include "model.h"

static void schedule(ModelInstance *m) {
    m->nextEventTimeDefined = true;
    m->nextEventTime = m->startTime + (m->data.counter + 1) * m->data.period;
}

void model_set_start_values(ModelInstance *m) {
    m->data.period = 1.0;
    m->data.level = 0.0;
    m->data.counter = 0;
}

void model_initialize(ModelInstance *m) { schedule(m); }

void model_event_update(ModelInstance *m) {
    if (m->nextEventTimeDefined && m->time >= m->nextEventTime - 1e-9 * m->data.period) {
        m->data.counter++;
        m->data.level = m->data.counter;
        schedule(m);
    }
}

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    switch (vr) {
    case VR_PERIOD: *value = m->data.period; return fmi2OK;
    case VR_LEVEL: *value = m->data.level; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    bool before_init = m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE);
    if (vr != VR_PERIOD || !before_init || value <= 0) {
        return fmi2Error;
    }
    m->data.period = value;
    return fmi2OK;
}

fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value) {
    if (vr != VR_COUNTER) {
        return fmi2Error;
    }
    *value = m->data.counter;
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

void model_get_continuous_states(const ModelInstance *m, double x[]) { (void)m, (void)x; }
void model_set_continuous_states(ModelInstance *m, const double x[]) { (void)m, (void)x; }
void model_get_derivatives(ModelInstance *m, double dx[]) { (void)m, (void)dx; }
void model_get_event_indicators(ModelInstance *m, double z[]) { (void)m, (void)z; }
