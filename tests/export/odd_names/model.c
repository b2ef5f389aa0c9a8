/* der('my var') = -k 'my var',  der(a[1]) = 'my var' - a[1],  y = 2 a[1]. */
#include "model.h"

void model_set_start_values(ModelInstance *m) {
    m->data.my_var = 1.0;
    m->data.a1 = 0.0;
    m->data.k = 0.5;
}

void model_initialize(ModelInstance *m) { m->nextEventTimeDefined = false; }

void model_event_update(ModelInstance *m) { (void)m; }

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    const ModelData *d = &m->data;
    switch (vr) {
    case VR_MY_VAR: *value = d->my_var; return fmi2OK;
    case VR_DER_MY_VAR: *value = -d->k * d->my_var; return fmi2OK;
    case VR_A1: *value = d->a1; return fmi2OK;
    case VR_DER_A1: *value = d->my_var - d->a1; return fmi2OK;
    case VR_K: *value = d->k; return fmi2OK;
    case VR_Y: *value = 2.0 * d->a1; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    switch (vr) {
    case VR_MY_VAR: m->data.my_var = value; return fmi2OK;
    case VR_A1: m->data.a1 = value; return fmi2OK;
    case VR_K: m->data.k = value; return fmi2OK;
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
    x[0] = m->data.my_var;
    x[1] = m->data.a1;
}

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    m->data.my_var = x[0];
    m->data.a1 = x[1];
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    dx[0] = -m->data.k * m->data.my_var;
    dx[1] = m->data.my_var - m->data.a1;
}

void model_get_event_indicators(ModelInstance *m, double z[]) { (void)m, (void)z; }

fmi2Status model_get_partial_derivative(ModelInstance *m, fmi2ValueReference unknown,
                                        fmi2ValueReference known, double *partial) {
    (void)m, (void)unknown, (void)known, (void)partial;
    return fmi2Error;
}
