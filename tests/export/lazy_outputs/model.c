/*
 * der(x) = -0.5 x, y = 2 x, evaluated lazily as OpenModelica 1.18's FMUs do: a change of the
 * states marks the point as not evaluated; fmi2GetReal then evaluates everything, but
 * fmi2GetDerivatives evaluates only the derivatives and still marks the point as evaluated, so
 * y read after it is the value at the previous point. (Not what FMI 2.0 asks for, but found in
 * the field.)
 */
#include "model.h"

static void evaluate_derivatives(ModelData *d) { d->der_x = -0.5 * d->x; }

static void evaluate_all(ModelData *d) {
    evaluate_derivatives(d);
    d->y = 2.0 * d->x;
}

void model_set_start_values(ModelInstance *m) {
    m->data.x = 1.0;
    m->data.need_update = true;
}

void model_initialize(ModelInstance *m) { m->nextEventTimeDefined = false; }

void model_event_update(ModelInstance *m) { (void)m; }

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    ModelData *d = &m->data;
    if (d->need_update) {
        evaluate_all(d);
        d->need_update = false;
    }
    switch (vr) {
    case VR_X: *value = d->x; return fmi2OK;
    case VR_DER_X: *value = d->der_x; return fmi2OK;
    case VR_Y: *value = d->y; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    if (vr != VR_X) {
        return fmi2Error;
    }
    m->data.x = value;
    m->data.need_update = true;
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

void model_set_continuous_states(ModelInstance *m, const double x[]) {
    m->data.x = x[0];
    m->data.need_update = true;
}

void model_get_derivatives(ModelInstance *m, double dx[]) {
    ModelData *d = &m->data;
    if (d->need_update) {
        evaluate_derivatives(d);   /* y is left as it was */
        d->need_update = false;
    }
    dx[0] = d->der_x;
}

void model_get_event_indicators(ModelInstance *m, double z[]) { (void)m, (void)z; }

fmi2Status model_get_partial_derivative(ModelInstance *m, fmi2ValueReference unknown,
                                        fmi2ValueReference known, double *partial) {
    (void)m, (void)unknown, (void)known, (void)partial;
    return fmi2Error;
}
