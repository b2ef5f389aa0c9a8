/* The compiled event loop (see event_loop.h). Each function mirrors its Python counterpart in
 * simulation/events.py, engine.py, solvers.py and system.py (FmuSystem), named in its comment;
 * arithmetic keeps their operand order, so the two loops agree to the bit (the build turns
 * floating-point contraction off). */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "loop.h"

/* A fixed step that would leave less than this fraction of itself before its limit is
 * stretched to the limit (solvers._SNAP). */
#define SNAP 1e-6
/* locate's iteration cap (events.locate's max_iterations). */
#define MAX_LOCATE_ITERATIONS 200


/* ---- FMI calls, each leaving its breadcrumb ------------------------------------------- */

static int failed(Loop *loop, core_call call, int status)
{
    loop->res->error = CORE_FMI_ERROR;
    loop->res->failed_call = (int)call;
    loop->res->failed_status = status;
    loop->res->error_time = loop->t;
    return 1;
}

#define FMI(loop, call, expr)                                                \
    do {                                                                     \
        const CoreFmu *fmu_ = (loop)->fmu;                                   \
        fmu_->call_slot[0] = fmu_->call_codes[call];                         \
        int status_ = (expr);                                                \
        fmu_->call_slot[0] = -fmu_->call_codes[call];                        \
        fmu_->ping_slot[0] = 0;                                              \
        if (status_ > 1) {                                                   \
            return failed((loop), (call), status_);                          \
        }                                                                    \
    } while (0)

#define TRY(expr)                                                            \
    do {                                                                     \
        if (expr) {                                                          \
            return 1;                                                        \
        }                                                                    \
    } while (0)

static int set_time(Loop *loop, double t)
{
    loop->fmu->time_slot[0] = t;
    FMI(loop, CALL_SET_TIME, loop->fmu->set_time(loop->fmu->component, t));
    return 0;
}

/* inputs.InputSignals.at: linear between samples, constant outside them. */
static void continuous_inputs_at(Loop *loop, double t)
{
    const CorePlan *p = loop->plan;
    size_t m = p->n_continuous_inputs, n = p->n_samples, i = loop->segment;
    const double *times = p->sample_times;
    const double *values;
    if (!(i + 1 < n && times[i] <= t && t < times[i + 1])) {
        if (t <= times[0]) {
            memcpy(loop->input_values, p->continuous_values, m * sizeof(double));
            return;
        }
        if (t >= times[n - 1]) {
            memcpy(loop->input_values, p->continuous_values + (n - 1) * m, m * sizeof(double));
            return;
        }
        size_t lo = 0, hi = n;      /* bisect_right(times, t) - 1 */
        while (lo < hi) {
            size_t mid = (lo + hi) / 2;
            if (t < times[mid]) {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        i = loop->segment = lo - 1;
    }
    values = p->continuous_values + i * m;
    for (size_t k = 0; k < m; ++k) {
        loop->input_values[k] = values[k] + (t - times[i]) * p->continuous_slopes[i * m + k];
    }
}

/* FmuSystem._at: the instance at (t, x), its continuous inputs at t. Where it already stands
 * there (the calls since the last put only read), the calls are left out. */
static int put_at(Loop *loop, double t, const double *x)
{
    const CoreFmu *f = loop->fmu;
    const CorePlan *p = loop->plan;
    if (loop->held && t == loop->held_t && memcmp(x, loop->held_x, loop->n * sizeof(double)) == 0) {
        return 0;
    }
    loop->held = 0;
    TRY(set_time(loop, t));
    if (p->n_continuous_inputs) {
        continuous_inputs_at(loop, t);
        FMI(loop, CALL_SET_REAL,
            f->set_real(f->component, p->continuous_input_vrs, p->n_continuous_inputs, loop->input_values));
    }
    if (loop->n) {
        FMI(loop, CALL_SET_CONTINUOUS_STATES, f->set_continuous_states(f->component, x, loop->n));
    }
    loop->held = 1;
    loop->held_t = t;
    memcpy(loop->held_x, x, loop->n * sizeof(double));
    return 0;
}

static double activated(int activation, double value)
{
    switch (activation) {
    case ACTIVATION_TANH:
        return tanh(value);
    case ACTIVATION_SIGMOID:        /* as neural/system.py: 0.5 tanh(z / 2) + 0.5 */
        return 0.5 * tanh(value * 0.5) + 0.5;
    case ACTIVATION_RELU:
        return value > 0.0 ? value : 0.0;
    default:
        return value;
    }
}

/* The fitted base term at the inputs z (neural/base_term.py, FittedTerm.point_kernel). */
static double base_term(const CoreCorrection *c, const double *z)
{
    double total = c->term_bias;
    size_t k = 0;
    while (k < c->n_terms) {
        int basis = c->term_basis[k];
        double sum = 0.0;
        for (; k < c->n_terms && c->term_basis[k] == basis; ++k) {
            double u = z[c->term_input[k]] - c->term_center[k];
            double phi = basis == BASIS_W ? u : basis == BASIS_ABS ? fabs(u)
                         : basis == BASIS_SIGNED_SQUARE ? u * fabs(u) : u * u;
            sum += c->term_coefficient[k] * phi;
        }
        total += sum;
    }
    return c->term_gate * total;
}

/* The correction (CoreCorrection) of the FMU's derivatives `der` at x; the instance stands at (t, x). */
static int correct(Loop *loop, const double *x, double *der)
{
    const CoreCorrection *c = loop->plan->correction;
    double *z = loop->network_in, *h = loop->network_a, *next = loop->network_b;
    if (c->n_variables) {
        FMI(loop, CALL_GET_REAL, loop->fmu->get_real(loop->fmu->component, c->variable_vrs, c->n_variables,
                                                      loop->variables));
    }
    for (size_t i = 0; i < c->n_inputs; ++i) {
        int index = c->input_index[i];
        z[i] = c->input_source[i] == SOURCE_STATE ? x[index]
               : c->input_source[i] == SOURCE_DERIVATIVE ? der[index] : loop->variables[index];
    }
    double base = c->term_gate != 0.0 ? base_term(c, z) : 0.0;
    const double *in = z, *w = c->weights, *b = c->biases;
    double *kept = loop->layer_outputs;     /* every layer's output kept for the sensitivities */
    if (kept != NULL) {
        memcpy(kept, z, c->n_inputs * sizeof(double));
        next = kept + c->n_inputs;
    }
    for (size_t layer = 0; layer < c->n_layers; ++layer) {
        int rows = c->layer_rows[layer], cols = c->layer_cols[layer];
        for (int j = 0; j < rows; ++j) {
            double sum = 0.0;
            for (int k = 0; k < cols; ++k) {
                sum += w[j * cols + k] * in[k];
            }
            next[j] = activated(c->layer_activation[layer], sum + b[j]);
        }
        w += (size_t)rows * cols;
        b += rows;
        in = next;
        next = kept != NULL ? next + rows : next == loop->network_b ? h : loop->network_b;
    }
    for (size_t k = 0; k < c->n_channels; ++k) {
        int state = c->channel_state[k];
        double network = c->n_layers ? in[k] : 0.0;
        loop->raw_channel[k] = der[state];
        double fmu = c->n_layers ? c->gate_fmu[k] * der[state] : der[state];
        der[state] = network + fmu + (c->n_channels == 1 ? base : 0.0);
    }
    return 0;
}

/* FmuSystem.derivatives, corrected where the plan says */
static int derivatives(Loop *loop, double t, const double *x, double *out)
{
    TRY(put_at(loop, t, x));
    if (loop->n) {
        FMI(loop, CALL_GET_DERIVATIVES, loop->fmu->get_derivatives(loop->fmu->component, out, loop->n));
    }
    if (loop->plan->correction != NULL) {
        TRY(correct(loop, x, out));
    }
    return 0;
}

int loop_derivatives(Loop *loop, double t, const double *x, double *out)
{
    return derivatives(loop, t, x, out);
}

double loop_activated(int activation, double value)
{
    return activated(activation, value);
}

int loop_fmu_values(Loop *loop, double t, const double *x, double *der, double *variables)
{
    const CoreCorrection *c = loop->plan->correction;
    TRY(put_at(loop, t, x));
    FMI(loop, CALL_GET_DERIVATIVES, loop->fmu->get_derivatives(loop->fmu->component, der, loop->n));
    if (c->n_variables) {
        FMI(loop, CALL_GET_REAL, loop->fmu->get_real(loop->fmu->component, c->variable_vrs, c->n_variables, variables));
    }
    return 0;
}

int loop_computed(Loop *loop, double t, const double *x)
{
    const CorePlan *p = loop->plan;
    TRY(put_at(loop, t, x));
    FMI(loop, CALL_GET_REAL, loop->fmu->get_real(loop->fmu->component, p->computed_vrs, p->n_computed, loop->computed));
    return 0;
}

/* FmuSystem.indicators */
static int indicators(Loop *loop, double t, const double *x, double *out)
{
    TRY(put_at(loop, t, x));
    if (loop->nz) {
        FMI(loop, CALL_GET_EVENT_INDICATORS, loop->fmu->get_event_indicators(loop->fmu->component, out, loop->nz));
    }
    loop->res->indicator_evaluations += 1;
    return 0;
}

/* ---- the fixed-step solvers (solvers.Euler, solvers.RK4) -------------------------------- */

static int dopri5_restart(Loop *loop, double t, const double *x, int keep_step);

/* Solver.restart (FixedStepSolver, DOPRI5): start again at (t, x) after an event; the first start
 * too (DOPRI5's proposed step is 0 then). */
static int solver_restart(Loop *loop, double t, const double *x, int keep_step)
{
    if (loop->hooks != NULL) {
        loop->hooks->restart(loop, t);
    }
    loop->st = loop->st_prev = t;
    memcpy(loop->sx, x, loop->n * sizeof(double));
    memcpy(loop->sx_prev, x, loop->n * sizeof(double));
    loop->dx_current = 0;
    if (loop->plan->solver == CORE_DOPRI5) {
        return dopri5_restart(loop, t, x, keep_step);
    }
    return 0;
}

/* RK4._derivative_here: the derivative at the solver's current point, evaluated once. */
static int derivative_here(Loop *loop)
{
    if (!loop->dx_current) {
        TRY(derivatives(loop, loop->st, loop->sx, loop->dx));
        loop->res->rhs_evaluations += 1;
        loop->dx_current = 1;
    }
    return 0;
}

static int dopri5_step(Loop *loop, double t_limit, double *t_reached);

/* FixedStepSolver.step with Euler._advance or RK4._advance / rk4_step; DOPRI5.step. */
static int solver_step(Loop *loop, double t_limit, double *t_reached)
{
    int64_t limit = loop->plan->max_rhs_evaluations;
    if (limit > 0 && loop->res->rhs_evaluations > limit) {
        loop->res->error = CORE_WORK_LIMIT;
        loop->res->error_time = loop->st;
        return 1;
    }
    if (loop->plan->solver == CORE_DOPRI5) {
        return dopri5_step(loop, t_limit, t_reached);
    }
    size_t n = loop->n;
    double t = loop->st, h = t_limit - t, t_new;
    double *x = loop->sx, *x_new = loop->x_new;
    if (h > loop->plan->step_size * (1.0 + SNAP)) {
        h = loop->plan->step_size;
        t_new = t + h;
    } else {
        t_new = t_limit;
    }
    if (loop->plan->solver == CORE_EULER) {
        TRY(derivatives(loop, t, x, loop->stage));
        loop->res->rhs_evaluations += 1;
        for (size_t i = 0; i < n; ++i) {
            x_new[i] = x[i] + h * loop->stage[i];
        }
    } else {
        double half = 0.5 * h, t_half = t + 0.5 * h, sixth = h / 6.0;
        TRY(derivative_here(loop));
        memcpy(loop->dx_prev, loop->dx, n * sizeof(double));
        loop->dx_current = 0;
        const double *k1 = loop->dx_prev;
        for (size_t i = 0; i < n; ++i) {
            loop->stage[i] = x[i] + half * k1[i];
        }
        TRY(derivatives(loop, t_half, loop->stage, loop->k2));
        for (size_t i = 0; i < n; ++i) {
            loop->stage[i] = x[i] + half * loop->k2[i];
        }
        TRY(derivatives(loop, t_half, loop->stage, loop->k3));
        for (size_t i = 0; i < n; ++i) {
            loop->stage[i] = x[i] + h * loop->k3[i];
        }
        TRY(derivatives(loop, t + h, loop->stage, loop->k4));
        loop->res->rhs_evaluations += 3;
        for (size_t i = 0; i < n; ++i) {
            x_new[i] = x[i] + sixth * (k1[i] + 2.0 * (loop->k2[i] + loop->k3[i]) + loop->k4[i]);
        }
    }
    if (loop->hooks != NULL) {
        TRY(loop->hooks->step(loop, t, h, x));
    }
    memcpy(loop->sx_prev, x, n * sizeof(double));
    memcpy(loop->sx, x_new, n * sizeof(double));
    loop->st_prev = t;
    loop->st = t_new;
    loop->res->steps += 1;
    *t_reached = t_new;
    return 0;
}

/* ---- DOPRI5 (solvers.DOPRI5): Dormand-Prince 5(4), its tables as there ------------------- */

static const double DP_C[7] = {0.0, 1.0 / 5, 3.0 / 10, 4.0 / 5, 8.0 / 9, 1.0, 1.0};
static const double DP_M[7][7] = {
    {1.0 / 5, 0, 0, 0, 0, 0, 0},
    {3.0 / 40, 9.0 / 40, 0, 0, 0, 0, 0},
    {44.0 / 45, -56.0 / 15, 32.0 / 9, 0, 0, 0, 0},
    {19372.0 / 6561, -25360.0 / 2187, 64448.0 / 6561, -212.0 / 729, 0, 0, 0},
    {9017.0 / 3168, -355.0 / 33, 46732.0 / 5247, 49.0 / 176, -5103.0 / 18656, 0, 0},
    {35.0 / 384, 0, 500.0 / 1113, 125.0 / 192, -2187.0 / 6784, 11.0 / 84, 0},
    {71.0 / 57600, 0, -71.0 / 16695, 71.0 / 1920, -17253.0 / 339200, 22.0 / 525, -1.0 / 40},
};
static const double DP_P[7][4] = {
    {1.0, -8048581381.0 / 2820520608, 8663915743.0 / 2820520608, -12715105075.0 / 11282082432},
    {0.0, 0.0, 0.0, 0.0},
    {0.0, 131558114200.0 / 32700410799, -68118460800.0 / 10900136933, 87487479700.0 / 32700410799},
    {0.0, -1754552775.0 / 470086768, 14199869525.0 / 1410260304, -10690763975.0 / 1880347072},
    {0.0, 127303824393.0 / 49829197408, -318862633887.0 / 49829197408, 701980252875.0 / 199316789632},
    {0.0, -282668133.0 / 205662961, 2019193451.0 / 616988883, -1453857185.0 / 822651844},
    {0.0, 40617522.0 / 29380423, -110615467.0 / 29380423, 69997945.0 / 29380423},
};

static double rms(const double *v, size_t n)
{
    double sum = 0.0;
    for (size_t i = 0; i < n; ++i) {
        sum += v[i] * v[i];
    }
    return sqrt(sum / n);
}

/* DOPRI5._initial_step: Hairer's starting-step heuristic, one extra derivative evaluation. */
static int dopri5_initial_step(Loop *loop, double *h)
{
    size_t n = loop->n;
    const CorePlan *p = loop->plan;
    double *x = loop->sx, *dx = loop->K, *scaled = loop->stage, *probe = loop->k2, *dx1 = loop->k3;
    if (n == 0) {
        *h = p->max_step;
        return 0;
    }
    for (size_t i = 0; i < n; ++i) {
        scaled[i] = x[i] / (p->atol + p->rtol * fabs(x[i]));
    }
    double d0 = rms(scaled, n);
    for (size_t i = 0; i < n; ++i) {
        scaled[i] = dx[i] / (p->atol + p->rtol * fabs(x[i]));
    }
    double d1 = rms(scaled, n);
    double h0 = d0 < 1e-5 || d1 < 1e-5 ? 1e-6 : 0.01 * d0 / d1;
    h0 = p->max_step < h0 ? p->max_step : h0;      /* min() as Python's: a NaN stays */
    for (size_t i = 0; i < n; ++i) {
        probe[i] = x[i] + h0 * dx[i];
    }
    TRY(derivatives(loop, loop->st + h0, probe, dx1));
    loop->res->rhs_evaluations += 1;
    for (size_t i = 0; i < n; ++i) {
        scaled[i] = (dx1[i] - dx[i]) / (p->atol + p->rtol * fabs(x[i]));
    }
    double d2 = rms(scaled, n) / h0, d = d2 > d1 ? d2 : d1;
    double h1 = d <= 1e-15 ? (1e-6 > h0 * 1e-3 ? 1e-6 : h0 * 1e-3) : pow(0.01 / d, 1.0 / 5);
    *h = 100 * h0;
    *h = h1 < *h ? h1 : *h;
    *h = p->max_step < *h ? p->max_step : *h;
    return 0;
}

/* DOPRI5.restart / _start: the derivative at (t, x) is the next step's first stage; a new first
 * step, or with keep_step the size reached so far, never larger than it. */
static int dopri5_restart(Loop *loop, double t, const double *x, int keep_step)
{
    double previous = loop->h;
    TRY(derivatives(loop, t, x, loop->K));
    loop->res->rhs_evaluations += 1;
    memcpy(loop->dx, loop->K, loop->n * sizeof(double));
    loop->stepped = 0;
    loop->dense_ready = 0;
    for (size_t i = 0; i < loop->n; ++i) {
        loop->abs_x[i] = fabs(x[i]);
    }
    if (keep_step && previous > 0.0) {
        loop->h = previous;
    } else {
        TRY(dopri5_initial_step(loop, &loop->h));
    }
    if (previous > 0.0 && previous < loop->h) {
        loop->h = previous;
    }
    return 0;
}

/* DOPRI5.step: one accepted step ending at or before t_limit. */
static int dopri5_step(Loop *loop, double t_limit, double *t_reached)
{
    const CorePlan *p = loop->plan;
    size_t n = loop->n;
    double *K = loop->K, *x = loop->sx, *x_new = loop->x_new, *stage = loop->stage;
    double t = loop->st, h = p->max_step < loop->h ? p->max_step : loop->h, h_wanted = h, t_new, err;
    int rejected = 0;
    if (!(h > 0.0)) {       /* no step size to start with (a degenerate tolerance) */
        loop->res->error = CORE_STEP_UNDERFLOW;
        loop->res->error_time = t;
        loop->res->error_step = h;
        return 1;
    }
    for (;;) {
        double remaining = t_limit - t;
        if (h >= remaining * (1.0 - SNAP)) {
            h = remaining;
            t_new = t_limit;
        } else {
            t_new = t + h;
        }
        for (int s = 0; s < 5; ++s) {
            for (size_t i = 0; i < n; ++i) {
                double sum = 0.0;
                for (int j = 0; j <= s; ++j) {
                    sum += h * DP_M[s][j] * K[j * n + i];
                }
                stage[i] = x[i] + sum;
            }
            TRY(derivatives(loop, t + DP_C[s + 1] * h, stage, K + (size_t)(s + 1) * n));
        }
        for (size_t i = 0; i < n; ++i) {
            double sum = 0.0;
            for (int j = 0; j < 6; ++j) {
                sum += h * DP_M[5][j] * K[j * n + i];
            }
            x_new[i] = x[i] + sum;
        }
        TRY(derivatives(loop, t_new, x_new, K + 6 * n));
        loop->res->rhs_evaluations += 6;
        err = 0.0;
        if (n) {
            double squares = 0.0;
            for (size_t i = 0; i < n; ++i) {
                double sum = 0.0;
                for (int j = 0; j < 7; ++j) {
                    sum += h * DP_M[6][j] * K[j * n + i];
                }
                loop->abs_new[i] = fabs(x_new[i]);
                double a = loop->abs_x[i], b = loop->abs_new[i];     /* numpy.maximum: NaN wins */
                double larger = isnan(a) || isnan(b) ? NAN : (a > b ? a : b);
                double e = sum / (p->atol + p->rtol * larger);
                squares += e * e;
            }
            err = sqrt(squares / n);
        }
        if (err <= 1.0) {
            break;
        }
        loop->res->rejected_steps += 1;
        rejected = 1;
        if (!isfinite(err)) {       /* the model failed somewhere: retreat, clear the stages */
            memset(K + n, 0, 6 * n * sizeof(double));
            h *= 0.2;
        } else {
            double factor = 0.9 * pow(err, -0.2);
            h *= factor > 0.2 ? factor : 0.2;
        }
        h_wanted = h;
        if (!(h >= 1e-14 * (fabs(t) > 1.0 ? fabs(t) : 1.0))) {     /* NaN too: no step size is left */
            loop->res->error = CORE_STEP_UNDERFLOW;
            loop->res->error_time = t;
            loop->res->error_step = h;
            return 1;
        }
    }
    double factor = 10.0;
    if (err != 0.0) {
        factor = 0.9 * pow(err, -0.2);
        factor = factor > 0.2 ? factor : 0.2;
        factor = factor < 10.0 ? factor : 10.0;
    }
    if (rejected) {
        factor = factor < 1.0 ? factor : 1.0;
    }
    double h_next = h * factor;
    if (t_new == t_limit && h < h_wanted) {     /* shortened to land on t_limit */
        h_next = h_wanted > h_next ? h_wanted : h_next;
    }
    loop->h = p->max_step < h_next ? p->max_step : h_next;
    loop->st_prev = t;
    loop->st = t_new;
    memcpy(loop->sx_prev, x, n * sizeof(double));
    memcpy(loop->dx_prev, K, n * sizeof(double));
    memcpy(loop->sx, x_new, n * sizeof(double));
    memcpy(loop->dx, K + 6 * n, n * sizeof(double));
    memcpy(loop->abs_x, loop->abs_new, n * sizeof(double));
    /* swap the stage buffers; the next step starts from this one's last stage */
    loop->K = loop->K_last;
    loop->K_last = K;
    memcpy(loop->K, K + 6 * n, n * sizeof(double));
    loop->dense_ready = 0;
    loop->stepped = 1;
    loop->res->steps += 1;
    *t_reached = t_new;
    return 0;
}

/* DOPRI5.interpolate: the continuous extension of order 4. */
static void dopri5_interpolate(Loop *loop, double t, double *out)
{
    size_t n = loop->n;
    if (!loop->stepped) {
        memcpy(out, loop->sx, n * sizeof(double));
        return;
    }
    if (!loop->dense_ready) {
        for (size_t i = 0; i < n; ++i) {
            for (int q = 0; q < 4; ++q) {
                double sum = 0.0;
                for (int j = 0; j < 7; ++j) {
                    sum += loop->K_last[j * n + i] * DP_P[j][q];
                }
                loop->Q[i * 4 + q] = sum;
            }
        }
        loop->dense_ready = 1;
    }
    double h = loop->st - loop->st_prev;
    double theta = h == 0.0 ? 1.0 : (t - loop->st_prev) / h;
    double powers[4] = {theta, theta * theta, pow(theta, 3), pow(theta, 4)};
    for (size_t i = 0; i < n; ++i) {
        const double *q = loop->Q + i * 4;
        out[i] = loop->sx_prev[i] + h * (q[0] * powers[0] + q[1] * powers[1] + q[2] * powers[2] + q[3] * powers[3]);
    }
}

/* Solver.interpolate: the state at t inside the last step (Euler: linear; RK4: cubic Hermite
 * from the derivatives at both ends, solvers.hermite; DOPRI5: its continuous extension). */
static int interpolate(Loop *loop, double t, double *out)
{
    size_t n = loop->n;
    double h = loop->st - loop->st_prev;
    double theta = h == 0.0 ? 1.0 : (t - loop->st_prev) / h;
    if (loop->plan->solver == CORE_DOPRI5) {
        dopri5_interpolate(loop, t, out);
        return 0;
    }
    if (loop->plan->solver == CORE_EULER) {
        for (size_t i = 0; i < n; ++i) {
            out[i] = loop->sx_prev[i] + theta * (loop->sx[i] - loop->sx_prev[i]);
        }
        return 0;
    }
    if (loop->st == loop->st_prev) {
        memcpy(out, loop->sx, n * sizeof(double));
        return 0;
    }
    TRY(derivative_here(loop));
    double t2 = theta * theta, t3 = t2 * theta;
    double a = 2 * t3 - 3 * t2 + 1, b = (t3 - 2 * t2 + theta) * h, c = -2 * t3 + 3 * t2, d = (t3 - t2) * h;
    for (size_t i = 0; i < n; ++i) {
        out[i] = a * loop->sx_prev[i] + b * loop->dx_prev[i] + c * loop->sx[i] + d * loop->dx[i];
    }
    return 0;
}

/* ---- recording ---------------------------------------------------------------------------- */

/* Room for `needed` entries in two arrays of one capacity (times and rows, event times and
 * kinds): both grow together, by doubling, only when full. */
static int grow(Loop *loop, size_t *capacity, size_t needed, void **a, size_t a_item, void **b, size_t b_item)
{
    if (needed <= *capacity) {
        return 0;
    }
    size_t wanted = *capacity ? *capacity : 64;
    while (wanted < needed) {
        wanted *= 2;
    }
    void *bigger_a = realloc(*a, wanted * a_item);
    if (bigger_a != NULL) {
        *a = bigger_a;
    }
    void *bigger_b = bigger_a != NULL ? realloc(*b, wanted * b_item) : NULL;
    if (bigger_b == NULL) {
        loop->res->error = CORE_NO_MEMORY;
        return 1;
    }
    *b = bigger_b;
    *capacity = wanted;
    return 0;
}

/* values_reader: the variables that change only at events, read once after each event. */
static int read_discrete(Loop *loop)
{
    const CoreFmu *f = loop->fmu;
    const CorePlan *p = loop->plan;
    for (int type = TYPE_REAL; type <= TYPE_BOOLEAN; ++type) {
        for (size_t k = 0; k < p->n_discrete; ++k) {
            if (p->discrete_types[k] != type) {
                continue;
            }
            double *into = loop->discrete_cache + k;
            if (type == TYPE_REAL) {
                FMI(loop, CALL_GET_REAL, f->get_real(f->component, p->discrete_vrs + k, 1, into));
            } else if (type == TYPE_INTEGER) {
                FMI(loop, CALL_GET_INTEGER, f->get_integer(f->component, p->discrete_vrs + k, 1, loop->integers));
                *into = (double)loop->integers[0];
            } else {
                FMI(loop, CALL_GET_BOOLEAN, f->get_boolean(f->component, p->discrete_vrs + k, 1, loop->integers));
                *into = loop->integers[0] ? 1.0 : 0.0;
            }
        }
    }
    loop->discrete_valid = 1;
    return 0;
}

/* FmuSystem._output_row: the recorded columns at (t, x), as count rows at times. */
static int record(Loop *loop, const double *times, size_t count, double t, const double *x)
{
    const CorePlan *p = loop->plan;
    CoreResult *r = loop->res;
    if (p->n_discrete && !loop->discrete_valid) {
        TRY(read_discrete(loop));
    }
    if (p->n_computed) {
        if (loop->continuous_mode) {    /* in event mode the FMU already holds (t, x) */
            TRY(put_at(loop, t, x));
        }
        FMI(loop, CALL_GET_REAL, loop->fmu->get_real(loop->fmu->component, p->computed_vrs, p->n_computed, loop->computed));
    }
    if (loop->derivative_columns) {     /* the corrected derivatives at (t, x) */
        if (loop->continuous_mode) {
            TRY(derivatives(loop, t, x, loop->recorded_dx));
        } else {                        /* in event mode the FMU already holds (t, x) */
            FMI(loop, CALL_GET_DERIVATIVES, loop->fmu->get_derivatives(loop->fmu->component, loop->recorded_dx, loop->n));
            if (p->correction != NULL) {
                TRY(correct(loop, x, loop->recorded_dx));
            }
        }
    }
    for (size_t j = 0; j < p->n_columns; ++j) {
        int index = p->column_index[j], kind = p->column_kind[j];
        loop->row[j] = kind == COLUMN_STATE ? x[index] : kind == COLUMN_DISCRETE ? loop->discrete_cache[index]
                       : kind == COLUMN_COMPUTED ? loop->computed[index] : loop->recorded_dx[index];
    }
    TRY(grow(loop, &r->row_capacity, r->n_rows + count, (void **)&r->times, sizeof(double), (void **)&r->rows,
             (p->n_columns ? p->n_columns : 1) * sizeof(double)));
    for (size_t k = 0; k < count; ++k) {
        if (loop->hooks != NULL) {
            TRY(loop->hooks->record(loop, t, x, r->n_rows));
        }
        r->times[r->n_rows] = times[k];
        memcpy(r->rows + r->n_rows * p->n_columns, loop->row, p->n_columns * sizeof(double));
        r->n_rows += 1;
    }
    return 0;
}

/* engine._Loop._record_reached: the output times reached (after the events at t). */
static int record_reached(Loop *loop, double t)
{
    const CorePlan *p = loop->plan;
    size_t i_next = loop->i_out;
    while (i_next < p->n_outputs && p->output_times[i_next] <= t + loop->eps) {
        i_next += 1;
    }
    if (i_next > loop->i_out) {
        size_t first = loop->i_out;
        loop->i_out = i_next;
        TRY(record(loop, p->output_times + first, i_next - first, t, loop->x));
    }
    return 0;
}

/* ---- what the sequence asks of its driver (engine._Loop) --------------------------------- */

/* step_limit: the stop, the next input kink, the next output time. */
static int step_limit(Loop *loop, double stop, double *target)
{
    const CorePlan *p = loop->plan;
    double t = loop->t;
    *target = stop;
    if (loop->i_out < p->n_outputs && p->output_times[loop->i_out] <= t + loop->eps) {
        TRY(record_reached(loop, t));
    }
    if (p->n_breakpoints) {
        while (loop->i_bp < p->n_breakpoints && p->breakpoints[loop->i_bp] <= t + loop->eps) {
            loop->i_bp += 1;
        }
        if (loop->i_bp < p->n_breakpoints && p->breakpoints[loop->i_bp] < *target) {
            *target = p->breakpoints[loop->i_bp];
        }
    }
    if (p->solver != CORE_DOPRI5 && loop->i_out < p->n_outputs && p->output_times[loop->i_out] < *target) {
        *target = p->output_times[loop->i_out];     /* a fixed-step solver ends a step at each output */
    }
    return 0;
}

/* events.crossed for any indicator. */
static int any_crossed(const double *z0, const double *z1, size_t nz)
{
    for (size_t i = 0; i < nz; ++i) {
        if ((z0[i] < 0.0 && z1[i] >= 0.0) || (z0[i] > 0.0 && z1[i] <= 0.0)) {
            return 1;
        }
    }
    return 0;
}

/* events._secant_earliest over the firing indicators, weighted. */
static double secant_earliest(const Loop *loop, double ta, double tb)
{
    const double *z0 = loop->z;
    int found = 0;
    double earliest = 0.0;
    for (size_t i = 0; i < loop->nz; ++i) {
        if (!((z0[i] < 0.0 && loop->zb[i] >= 0.0) || (z0[i] > 0.0 && loop->zb[i] <= 0.0))) {
            continue;
        }
        double za = loop->wa[i] * loop->za[i], zb = loop->wb[i] * loop->zb[i];
        double root = tb - zb * (tb - ta) / (zb - za);
        if (isfinite(root) && (!found || root < earliest)) {
            earliest = root;
            found = 1;
        }
    }
    if (!found) {
        return 0.5 * (ta + tb);
    }
    double bounded = ta > earliest ? ta : earliest;     /* min(max(roots.min(), ta), tb) */
    return tb < bounded ? tb : bounded;
}

/* engine._Loop._indicators_on_step: the indicators on the last step's dense output. */
static int indicators_on_step(Loop *loop, double t, double *out)
{
    TRY(interpolate(loop, t, loop->interpolated));
    return indicators(loop, t, loop->interpolated, out);
}

/* events.locate: the earliest crossing in (t0, t1] by a vector Illinois iteration; the right end
 * of the final bracket (t, in *t_event) and the indicators there (in loop->zb). */
static int locate(Loop *loop, double t0, double t1, const double *z1, double tolerance, double *t_event)
{
    size_t nz = loop->nz;
    double ta = t0, tb = t1, width_before = t1 - t0;
    int last_side = 0, evaluations = 0;
    memcpy(loop->za, loop->z, nz * sizeof(double));
    memcpy(loop->zb, z1, nz * sizeof(double));
    for (size_t i = 0; i < nz; ++i) {
        loop->wa[i] = loop->wb[i] = 1.0;
    }
    while (tb - ta > tolerance && evaluations < MAX_LOCATE_ITERATIONS) {
        double t_trial = secant_earliest(loop, ta, tb);
        if (evaluations % 3 == 2 && tb - ta > 0.5 * width_before) {
            t_trial = 0.5 * (ta + tb);      /* slow progress: bisect */
        }
        if (evaluations % 3 == 2) {
            width_before = tb - ta;
        }
        double margin = 0.25 * tolerance, low = ta + margin, high = tb - margin;
        t_trial = low > t_trial ? low : t_trial;
        t_trial = high < t_trial ? high : t_trial;
        TRY(indicators_on_step(loop, t_trial, loop->z_trial));
        evaluations += 1;
        if (any_crossed(loop->z, loop->z_trial, nz)) {
            tb = t_trial;
            memcpy(loop->zb, loop->z_trial, nz * sizeof(double));
            for (size_t i = 0; i < nz; ++i) {
                loop->wb[i] = 1.0;
                if (last_side == 1) {
                    loop->wa[i] *= 0.5;
                }
            }
            last_side = 1;
        } else {
            ta = t_trial;
            memcpy(loop->za, loop->z_trial, nz * sizeof(double));
            for (size_t i = 0; i < nz; ++i) {
                loop->wa[i] = 1.0;
                if (last_side == -1) {
                    loop->wb[i] *= 0.5;
                }
            }
            last_side = -1;
        }
    }
    *t_event = tb;
    return 0;
}

static double tolerance_at(const Loop *loop, double t)
{
    /* events.time_tolerance */
    double scale = loop->plan->time_scale, magnitude = fabs(t);
    return loop->plan->relative_time_tolerance * (scale > magnitude ? scale : magnitude);
}

/* EventSequence._cut with engine._Loop.cut_at_state_event: the step cut at its earliest state
 * event; the engine's state there. z_end holds the indicators at the new end. */
static int cut_at_state_event(Loop *loop, double t_start, double *t_end)
{
    loop->cuts_in_a_row += 1;
    if (loop->cuts_in_a_row > loop->plan->max_cuts_in_a_row) {
        loop->res->error = CORE_CHATTERING;
        loop->res->error_time = *t_end;
        return 1;
    }
    double tolerance = tolerance_at(loop, *t_end), relative = 1e-12 * (*t_end - t_start);
    tolerance = relative > tolerance ? relative : tolerance;
    double t_event;
    TRY(locate(loop, t_start, *t_end, loop->z_end, tolerance, &t_event));
    memcpy(loop->z_end, loop->zb, loop->nz * sizeof(double));
    if (t_event != *t_end) {
        TRY(interpolate(loop, t_event, loop->x));
    }
    *t_end = t_event;
    return 0;
}

/* engine._Loop.completed_step with FmuSystem.completed_step: output times inside the step from
 * the dense output, then fmi2CompletedIntegratorStep. */
static int completed_step(Loop *loop, int *step_event, int *terminate)
{
    const CorePlan *p = loop->plan;
    double t = loop->t;
    while (loop->i_out < p->n_outputs && p->output_times[loop->i_out] < t - loop->eps) {
        double time = p->output_times[loop->i_out];
        TRY(interpolate(loop, time, loop->interpolated));
        TRY(record(loop, &time, 1, time, loop->interpolated));
        loop->i_out += 1;
    }
    *step_event = *terminate = 0;
    if (p->needs_completed_step) {
        TRY(put_at(loop, t, loop->x));
        FMI(loop, CALL_COMPLETED_INTEGRATOR_STEP,
            loop->fmu->completed_integrator_step(loop->fmu->component, 1, step_event, terminate));
    }
    return 0;
}

/* inputs.InputSignals.discrete_at, set by FmuSystem.handle_event before the event iteration. */
static int set_discrete_inputs(Loop *loop, double t)
{
    const CoreFmu *f = loop->fmu;
    const CorePlan *p = loop->plan;
    size_t lo = 0, hi = p->n_samples;
    while (lo < hi) {
        size_t mid = (lo + hi) / 2;
        if (t < p->sample_times[mid]) {
            hi = mid;
        } else {
            lo = mid + 1;
        }
    }
    size_t row = lo > 0 ? lo - 1 : 0;
    for (size_t k = 0; k < p->n_discrete_inputs; ++k) {
        const unsigned int *vr = p->discrete_input_vrs + k;
        double value = p->discrete_values[row * p->n_discrete_inputs + k];
        if (p->discrete_input_types[k] == TYPE_REAL) {
            FMI(loop, CALL_SET_REAL, f->set_real(f->component, vr, 1, &value));
        } else if (p->discrete_input_types[k] == TYPE_INTEGER) {
            int integer = (int)value;
            FMI(loop, CALL_SET_INTEGER, f->set_integer(f->component, vr, 1, &integer));
        } else {
            int boolean = value != 0.0;
            FMI(loop, CALL_SET_BOOLEAN, f->set_boolean(f->component, vr, 1, &boolean));
        }
    }
    return 0;
}

/* FmuInstance.update_discrete_states: the event iteration, merged over its passes. */
static int event_iteration(Loop *loop, core_event_info *merged)
{
    const CoreFmu *f = loop->fmu;
    core_event_info info;
    int values_changed = 0, iterations = 0;
    for (;;) {
        info.newDiscreteStatesNeeded = 1;
        FMI(loop, CALL_NEW_DISCRETE_STATES, f->new_discrete_states(f->component, &info));
        iterations += 1;
        values_changed |= info.valuesOfContinuousStatesChanged;
        if (info.terminateSimulation || !info.newDiscreteStatesNeeded) {
            break;
        }
    }
    *merged = info;
    merged->valuesOfContinuousStatesChanged = values_changed;
    loop->res->event_iterations += iterations;
    return 0;
}

/* engine._Loop.event with FmuSystem.handle_event and events.event_mode. */
static int event(Loop *loop, int kind)
{
    const CoreFmu *f = loop->fmu;
    const CorePlan *p = loop->plan;
    CoreResult *r = loop->res;
    double t = loop->t;
    TRY(grow(loop, &r->event_capacity, r->n_events + 1, (void **)&r->event_times, sizeof(double),
             (void **)&r->event_kinds, sizeof(int)));
    r->event_times[r->n_events] = t;
    r->event_kinds[r->n_events] = kind;
    r->n_events += 1;
    if (p->record_events) {
        TRY(record(loop, &t, 1, t, loop->x));
    }
    TRY(put_at(loop, t, loop->x));
    loop->continuous_mode = 0;
    loop->discrete_valid = 0;
    loop->held = 0;         /* the event may change the states and the discrete inputs */
    FMI(loop, CALL_ENTER_EVENT_MODE, f->enter_event_mode(f->component));
    if (p->n_discrete_inputs) {
        TRY(set_discrete_inputs(loop, t));
    }
    core_event_info info;
    TRY(event_iteration(loop, &info));
    if (loop->hooks != NULL) {
        loop->hooks->after_event(loop, info.valuesOfContinuousStatesChanged);
    }
    if (!info.terminateSimulation) {
        FMI(loop, CALL_ENTER_CONTINUOUS_TIME_MODE, f->enter_continuous_time_mode(f->component));
    }
    if (loop->n) {      /* the event may have reset the states */
        FMI(loop, CALL_GET_CONTINUOUS_STATES, f->get_continuous_states(f->component, loop->x, loop->n));
    }
    if (info.terminateSimulation) {
        loop->next_event = INFINITY;
        loop->terminated = 1;
    } else {
        loop->continuous_mode = 1;
        double next = info.nextEventTimeDefined ? info.nextEventTime : INFINITY;
        for (size_t k = 0; k < p->n_input_events; ++k) {   /* the next change of a discrete input */
            if (p->input_event_times[k] > t) {
                next = p->input_event_times[k] < next ? p->input_event_times[k] : next;
                break;
            }
        }
        loop->next_event = next;
    }
    if (p->record_events) {
        TRY(record(loop, &t, 1, t, loop->x));
    }
    if (!loop->terminated) {
        TRY(solver_restart(loop, t, loop->x, kind == EVENT_TIME));
        if (loop->z != NULL) {      /* the indicators after the event: the next step's reference */
            TRY(indicators(loop, t, loop->x, loop->z));
        }
    }
    return 0;
}

/* ---- the sequence (events.EventSequence.towards, driven by engine._Loop.run) -------------- */

static int is_due(const Loop *loop, double event_time, double t)
{
    return event_time <= t + tolerance_at(loop, t);
}

static int towards(Loop *loop, double limit)
{
    const CorePlan *p = loop->plan;
    CoreResult *r = loop->res;
    double at_limit = limit - tolerance_at(loop, limit);
    while (!loop->terminated) {
        double t = loop->t;
        if (is_due(loop, loop->next_event, t)) {
            if (loop->next_event > t) {
                loop->t = loop->next_event;     /* a time event a rounding error ahead is now */
            }
            loop->events_here += 1;
            if (loop->events_here > p->max_events_at_one_time) {
                r->error = CORE_EVENT_STORM;
                r->error_time = loop->t;
                return 1;
            }
            r->time_events += 1;
            TRY(event(loop, EVENT_TIME));
            continue;
        }
        if (t >= at_limit) {
            return 0;
        }
        double end, t_end;
        TRY(step_limit(loop, limit, &end));
        TRY(solver_step(loop, loop->next_event < end ? loop->next_event : end, &t_end));
        memcpy(loop->x, loop->sx, loop->n * sizeof(double));
        int state_event = 0;
        if (loop->z != NULL) {      /* the indicators at the step's end: a sign change cuts it */
            TRY(indicators(loop, t_end, loop->x, loop->z_end));
            if (any_crossed(loop->z, loop->z_end, loop->nz)) {
                state_event = 1;
                TRY(cut_at_state_event(loop, t, &t_end));
            } else {
                loop->cuts_in_a_row = 0;
            }
            double *swap = loop->z;
            loop->z = loop->z_end;
            loop->z_end = swap;
        }
        loop->t = t_end;
        loop->events_here = 0;
        int step_event = 0;
        if (t_end != t) {
            int terminate;
            TRY(completed_step(loop, &step_event, &terminate));
            if (terminate) {
                loop->terminated = 1;
                return 0;
            }
        }
        if (is_due(loop, loop->next_event, t_end)) {
            continue;   /* a time event is due now: the next pass handles it, and any crossing with it */
        }
        if (state_event) {
            r->state_events += 1;
            r->step_events += step_event;
            TRY(event(loop, EVENT_STATE));
        } else if (step_event) {
            r->step_events += 1;
            TRY(event(loop, EVENT_STEP));
        } else if (loop->i_bp < p->n_breakpoints && loop->t >= p->breakpoints[loop->i_bp] - loop->eps) {
            TRY(solver_restart(loop, loop->t, loop->x, 0));     /* the inputs' slope changes here */
        }
    }
    return 0;
}

/* ---- set-up and the run --------------------------------------------------------------------- */

static double *take(double **pool, size_t count)
{
    double *block = *pool;
    *pool += count;
    return block;
}

int core_run(const CoreFmu *fmu, const CorePlan *plan, CoreResult *result)
{
    return loop_run(fmu, plan, result, NULL);
}

int loop_run(const CoreFmu *fmu, const CorePlan *plan, CoreResult *result, const SensitivityHooks *hooks)
{
    Loop loop;
    memset(&loop, 0, sizeof(loop));
    memset(result, 0, sizeof(*result));
    size_t n = plan->n_states, nz = plan->n_indicators;
    const CoreCorrection *c = plan->correction;
    size_t width = 0, n_inputs = c ? c->n_inputs : 0, n_variables = c ? c->n_variables : 0;
    for (size_t layer = 0; c != NULL && layer < c->n_layers; ++layer) {
        width = (size_t)c->layer_rows[layer] > width ? (size_t)c->layer_rows[layer] : width;
    }
    size_t words = 33 * n + 7 * nz + plan->n_continuous_inputs + plan->n_discrete + plan->n_computed
                   + plan->n_columns + n_inputs + 2 * width + n_variables + (c ? c->n_channels : 0) + 1;
    double *memory = calloc(words, sizeof(double));
    int *integers = calloc(1, sizeof(int));
    result->x = calloc(n ? n : 1, sizeof(double));
    if (memory == NULL || integers == NULL || result->x == NULL) {
        free(memory);
        free(integers);
        result->error = CORE_NO_MEMORY;
        return result->error;
    }
    double *pool = memory;
    loop.fmu = fmu;
    loop.plan = plan;
    loop.res = result;
    loop.n = n;
    loop.nz = nz;
    loop.eps = plan->relative_time_tolerance * plan->time_scale;
    loop.x = take(&pool, n);
    loop.sx = take(&pool, n);
    loop.sx_prev = take(&pool, n);
    loop.dx = take(&pool, n);
    loop.dx_prev = take(&pool, n);
    loop.x_new = take(&pool, n);
    loop.stage = take(&pool, n);
    loop.k2 = take(&pool, n);
    loop.k3 = take(&pool, n);
    loop.k4 = take(&pool, n);
    loop.interpolated = take(&pool, n);
    loop.held_x = take(&pool, n);
    loop.K = take(&pool, 7 * n);
    loop.K_last = take(&pool, 7 * n);
    loop.abs_x = take(&pool, n);
    loop.abs_new = take(&pool, n);
    loop.Q = take(&pool, 4 * n);
    double *z_a = take(&pool, nz), *z_b = take(&pool, nz);
    loop.za = take(&pool, nz);
    loop.zb = take(&pool, nz);
    loop.z_trial = take(&pool, nz);
    loop.wa = take(&pool, nz);
    loop.wb = take(&pool, nz);
    loop.input_values = take(&pool, plan->n_continuous_inputs);
    loop.discrete_cache = take(&pool, plan->n_discrete);
    loop.computed = take(&pool, plan->n_computed);
    loop.row = take(&pool, plan->n_columns);
    loop.recorded_dx = take(&pool, n);
    loop.network_in = take(&pool, n_inputs);
    loop.network_a = take(&pool, width);
    loop.network_b = take(&pool, width);
    loop.variables = take(&pool, n_variables);
    loop.raw_channel = take(&pool, c ? c->n_channels : 0);
    loop.hooks = hooks;
    loop.sens = hooks != NULL ? hooks->sens : NULL;
    loop.layer_outputs = hooks != NULL ? hooks->layer_outputs : NULL;
    for (size_t j = 0; j < plan->n_columns; ++j) {
        loop.derivative_columns |= plan->column_kind[j] == COLUMN_DERIVATIVE;
    }
    loop.integers = integers;
    loop.continuous_mode = 1;
    loop.t = plan->start;
    loop.next_event = plan->next_event;
    memcpy(loop.x, plan->x0, n * sizeof(double));
    int failed_run = solver_restart(&loop, plan->start, plan->x0, 0);
    if (nz) {       /* the indicators at the start: the first step's reference */
        loop.z = z_a;
        loop.z_end = z_b;
        failed_run = failed_run || indicators(&loop, plan->start, loop.x, loop.z);
    }
    if (!failed_run) {
        failed_run = towards(&loop, plan->stop);
    }
    if (!failed_run && !loop.terminated) {
        failed_run = record_reached(&loop, loop.t);
    }
    if (!failed_run && loop.terminated) {   /* what the model reached, if not recorded yet */
        int recorded = result->n_rows > 0 && fabs(result->times[result->n_rows - 1] - loop.t) <= loop.eps;
        if (!recorded) {
            failed_run = record(&loop, &loop.t, 1, loop.t, loop.x);
        }
    }
    result->t = loop.t;
    result->next_event = loop.next_event;
    result->terminated = loop.terminated;
    memcpy(result->x, loop.x, n * sizeof(double));
    free(memory);
    free(integers);
    return result->error;
}

void core_free_result(CoreResult *result)
{
    free(result->x);
    free(result->times);
    free(result->rows);
    free(result->event_times);
    free(result->event_kinds);
    memset(result, 0, sizeof(*result));
}
