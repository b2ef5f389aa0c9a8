/*
 * Event corner cases, all with analytic answers (t0 = start time, defaults in brackets).
 *
 * 1. Time event at the start time: model_initialize schedules nextEventTime = t0, so the
 *    event is handled in the initial event iteration after fmi2ExitInitializationMode.
 *    That iteration needs two fmi2NewDiscreteStates calls (newDiscreteStatesNeeded):
 *    start_ticks becomes 1 in the first, start_ticks_seen follows in the second.
 *    Expected after initialization: start_ticks = start_ticks_seen = 1.
 *
 * 2. Two event indicators crossing zero at the same instant: z0 = p - p_max and
 *    z1 = 2 (p_max - p) describe the same relation (as a Modelica tool emits for a
 *    when-clause and an if-expression on one condition), crossing in opposite directions.
 *
 * 3. An event that changes continuous states: der(p) = 1 and p := 0 when p reaches p_max,
 *    so state events happen at t0 + k p_max, k = 1, 2, ...  [1, 2, 3] and
 *    p(t) = (t - t0) mod p_max.
 *
 * 4. A step event: once t >= t_step [0.5], fmi2CompletedIntegratorStep requests event
 *    mode; the event is handled at the end of that integrator step, so step_event_time is
 *    the first step end >= t_step (exactly t_step when the importer steps onto it).
 *    der(r) = +1 before, -1 after: r(t) = (t - t0) until t_s, then 2 t_s - t - t0.
 *
 * 5. Termination: a time event at t_terminate [3.5] sets terminateSimulation, so a
 *    simulation with a later stop time ends at t_terminate with resets = 3.
 */
#include "model.h"

/* Round-off tolerance for comparing the importer's event time with a scheduled time. */
#define TIME_EPSILON 1e-9

void model_set_start_values(ModelInstance *m) {
    ModelData *d = &m->data;
    d->p = 0.0;
    d->r = 0.0;
    d->p_max = 1.0;
    d->t_step = 0.5;
    d->t_terminate = 3.5;
    d->step_event_time = -1.0;
    d->resets = 0;
    d->start_ticks = 0;
    d->start_ticks_seen = 0;
    d->step_event_done = false;
    d->terminate_pending = false;
}

void model_initialize(ModelInstance *m) {
    m->nextEventTimeDefined = true;
    m->nextEventTime = m->startTime; /* corner case 1 */
}

static bool time_event_due(const ModelInstance *m) {
    return m->nextEventTimeDefined && m->time >= m->nextEventTime - TIME_EPSILON;
}

static void handle_time_event(ModelInstance *m) {
    ModelData *d = &m->data;
    if (d->terminate_pending) {
        m->terminateSimulation = true;
        m->nextEventTimeDefined = false;
        return;
    }
    d->start_ticks++;
    m->newDiscreteStatesNeeded = true; /* start_ticks_seen follows in the next iteration */
    d->terminate_pending = true;
    m->nextEventTime = d->t_terminate;
}

void model_event_update(ModelInstance *m) {
    ModelData *d = &m->data;
    if (d->start_ticks_seen != d->start_ticks) {
        d->start_ticks_seen = d->start_ticks;
    }
    if (time_event_due(m)) {
        handle_time_event(m);
    }
    if (d->p >= d->p_max) {
        d->p = 0.0;
        d->resets++;
        m->valuesOfContinuousStatesChanged = true;
    }
    if (!d->step_event_done && m->time >= d->t_step) {
        d->step_event_done = true;
        d->step_event_time = m->time;
    }
    model_log(m, fmi2OK, "logEvents", "event at t=%g: resets=%d start_ticks=%d%s", m->time,
              d->resets, d->start_ticks, m->terminateSimulation ? " (terminate)" : "");
}

bool model_completed_integrator_step(ModelInstance *m) {
    return !m->data.step_event_done && m->time >= m->data.t_step;
}

fmi2Status model_get_real(ModelInstance *m, fmi2ValueReference vr, double *value) {
    const ModelData *d = &m->data;
    switch (vr) {
    case VR_P: *value = d->p; return fmi2OK;
    case VR_DER_P: *value = 1.0; return fmi2OK;
    case VR_R: *value = d->r; return fmi2OK;
    case VR_DER_R: *value = d->step_event_done ? -1.0 : 1.0; return fmi2OK;
    case VR_P_MAX: *value = d->p_max; return fmi2OK;
    case VR_T_STEP: *value = d->t_step; return fmi2OK;
    case VR_T_TERMINATE: *value = d->t_terminate; return fmi2OK;
    case VR_STEP_EVENT_TIME: *value = d->step_event_time; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_real(ModelInstance *m, fmi2ValueReference vr, double value) {
    ModelData *d = &m->data;
    if (!(m->state & (STATE_INSTANTIATED | STATE_INITIALIZATION_MODE))) {
        return fmi2Error; /* everything settable is a fixed parameter or a start value */
    }
    switch (vr) {
    case VR_P: d->p = value; return fmi2OK;
    case VR_R: d->r = value; return fmi2OK;
    case VR_P_MAX: if (value <= 0) return fmi2Error; d->p_max = value; return fmi2OK;
    case VR_T_STEP: d->t_step = value; return fmi2OK;
    case VR_T_TERMINATE: d->t_terminate = value; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_get_integer(ModelInstance *m, fmi2ValueReference vr, int *value) {
    const ModelData *d = &m->data;
    switch (vr) {
    case VR_RESETS: *value = d->resets; return fmi2OK;
    case VR_START_TICKS: *value = d->start_ticks; return fmi2OK;
    case VR_START_TICKS_SEEN: *value = d->start_ticks_seen; return fmi2OK;
    default: return fmi2Error;
    }
}

fmi2Status model_set_integer(ModelInstance *m, fmi2ValueReference vr, int value) {
    (void)m, (void)vr, (void)value;
    return fmi2Error;
}

fmi2Status model_get_boolean(ModelInstance *m, fmi2ValueReference vr, bool *value) {
    if (vr != VR_STEP_EVENT_DONE) {
        return fmi2Error;
    }
    *value = m->data.step_event_done;
    return fmi2OK;
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
    dx[1] = m->data.step_event_done ? -1.0 : 1.0;
}

void model_get_event_indicators(ModelInstance *m, double z[]) {
    z[0] = m->data.p - m->data.p_max;
    z[1] = 2.0 * (m->data.p_max - m->data.p);
}
