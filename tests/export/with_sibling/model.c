/* der(x) = -rate x with the rate from the sibling library (libsibling.so beside this one). */
#include "model.h"

double sibling_rate(void);

void model_set_start_values(ModelInstance *m) { m->data.x = 1.0; }

void model_initialize(ModelInstance *m) { m->nextEventTimeDefined = false; }

void model_event_update(ModelInstance *m) { (void)m; }

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    switch (vr) {
    case VR_X: *value = m->data.x; return fmi2OK;
    case VR_DER_X: *value = -sibling_rate() * m->data.x; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    if (vr != VR_X) {
        return fmi2Error;
    }
    m->data.x = value;
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

void model_get_continuous_states(const ModelInstance *m, double x[]) { x[0] = m->data.x; }

void model_set_continuous_states(ModelInstance *m, const double x[]) { m->data.x = x[0]; }

void model_get_derivatives(ModelInstance *m, double dx[]) { dx[0] = -sibling_rate() * m->data.x; }

void model_get_event_indicators(ModelInstance *m, double z[]) { (void)m, (void)z; }

fmi2Status model_get_partial_derivative(ModelInstance *m, fmi2ValueReference unknown,
                                        fmi2ValueReference known, double *partial) {
    (void)m, (void)unknown, (void)known, (void)partial;
    return fmi2Error;
}
