/* Forward sensitivities of a corrected system (a NeuralFMU) to its correction's parameters, in the
 * event loop's own steps (see core_gradient_run in event_loop.h).
 *
 * theta: the layers' W and b (row-major, layer after layer), then the FMU gate of each channel.
 * S = dx/dtheta [n][P] is stepped beside the states with the solver's own stages:
 *     dS/dt = J S + F,   F = df/dtheta from the network's weights (backpropagation),
 *     J = df/dx: the FMU's derivatives and the variables the network reads by forward differences,
 *     through the network by its input gradient (backpropagation too).
 * Time events, step events and input kinks pass S on unchanged; a state reset at an event is
 * counted (the caller uses another gradient then); state events are passed on without the
 * event-time term. At each recorded row the weighted outputs' sensitivities are summed into the
 * gradient: sum over columns of w dy/dtheta, with dy/dx of a computed variable by differences. */
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "loop.h"

struct Sensitivity {
    size_t n, P, n_columns, n_outputs, width_total;
    const double *weights;          /* [n_outputs][n_columns] by recorded row, NULL: no sensitivities */
    double *gradient;               /* [P] */
    int64_t resets;
    double st, st_prev;             /* the times of S and S_prev */
    double *S, *S_prev, *S_stage, *K, *K_sum, *F;   /* [n][P] each; F: [n_channels][P] */
    double *J, *f0, *fp, *xp, *xs, *v;              /* J [n][n]; the others [n] */
    double *activations, *delta, *delta_next;       /* z and the layers' outputs; backward */
    double *input_gradient;         /* [n_channels][n_inputs]: d(network + base)/dz */
    double *der0, *J_fmu;           /* the FMU's derivatives [n] and their Jacobian [n][n] */
    double *vars0, *vars_p, *dvars; /* the network's FMU variables [m], perturbed, d/dx [m][n] */
    double *y0;                     /* the computed columns at the nominal point */
    /* where J and F were last taken: a grid point's record and the next step's first stage share it */
    double lin_t, *lin_x;
    int lin_valid;
};

/* A perturbation of a state for forward differences. */
static double fd_step(double value)
{
    return sqrt(DBL_EPSILON) * (fabs(value) > 1.0 ? fabs(value) : 1.0);
}

static double activation_slope(int activation, double out)
{
    switch (activation) {
    case ACTIVATION_TANH:
        return 1.0 - out * out;
    case ACTIVATION_SIGMOID:
        return out * (1.0 - out);
    case ACTIVATION_RELU:
        return out > 0.0 ? 1.0 : 0.0;
    default:
        return 1.0;
    }
}

/* gradient += d(base term)/dz (see base_term in event_loop.c). */
static void base_gradient(const CoreCorrection *c, const double *z, double *gradient)
{
    for (size_t k = 0; k < c->n_terms; ++k) {
        double u = z[c->term_input[k]] - c->term_center[k];
        int basis = c->term_basis[k];
        double slope = basis == BASIS_W ? 1.0 : basis == BASIS_ABS ? (u > 0.0) - (u < 0.0)
                       : basis == BASIS_SIGNED_SQUARE ? 2.0 * fabs(u) : 2.0 * u;
        gradient[c->term_input[k]] += c->term_gate * c->term_coefficient[k] * slope;
    }
}

/* Layer l's part of a channel's row of F (dW = delta a^T, db = delta, for the layer's input a),
 * and delta carried back to the layer's input: into `back` (times the previous layer's activation
 * slope), or for the first layer the network's input gradient. */
static void layer_backward(const CoreCorrection *c, size_t l, const double *W, const double *a,
                           const double *delta, double *dW, double *back, int first)
{
    int rows = c->layer_rows[l], cols = c->layer_cols[l];
    double *db = dW + (size_t)rows * cols;
    for (int j = 0; j < rows; ++j) {
        if (delta[j] == 0.0) {
            continue;
        }
        for (int k = 0; k < cols; ++k) {
            dW[j * cols + k] = delta[j] * a[k];
        }
        db[j] = delta[j];
    }
    for (int k = 0; k < cols; ++k) {
        double sum = 0.0;
        for (int j = 0; j < rows; ++j) {
            sum += W[j * cols + k] * delta[j];
        }
        back[k] = first ? sum : sum * activation_slope(c->layer_activation[l - 1], a[k]);
    }
}

/* Row `channel` of F (df_channel/dtheta) and its input gradient, by backpropagation through the
 * layers' outputs that correct() kept at the nominal point (s->activations: z, then each layer). */
static void channel_row(Loop *loop, Sensitivity *s, size_t channel)
{
    const CoreCorrection *c = loop->plan->correction;
    const double *outputs = s->activations;
    double *row = s->F + channel * s->P, *delta = s->delta, *next = s->delta_next;
    memset(row, 0, s->P * sizeof(double));
    size_t L = c->n_layers, offset_params = s->P - c->n_channels, offset_out = s->width_total;
    const double *W = c->weights;
    for (size_t l = 0; l < L; ++l) {
        W += (size_t)c->layer_rows[l] * c->layer_cols[l];
    }
    int rows = c->layer_rows[L - 1];
    offset_out -= rows;
    for (int j = 0; j < rows; ++j) {
        delta[j] = j == (int)channel ? activation_slope(c->layer_activation[L - 1], outputs[offset_out + j]) : 0.0;
    }
    for (size_t l = L; l-- > 0;) {
        rows = c->layer_rows[l];
        int cols = c->layer_cols[l];
        W -= (size_t)rows * cols;
        offset_out -= cols;             /* now the layer's input */
        offset_params -= (size_t)rows * cols + rows;
        double *back = l == 0 ? s->input_gradient + channel * c->n_inputs : next;
        layer_backward(c, l, W, outputs + offset_out, delta, row + offset_params, back, l == 0);
        next = delta;
        delta = back;
    }
    row[s->P - c->n_channels + channel] = loop->raw_channel[channel];
}

/* F and the input gradients of every channel, with the base term's (one channel only). */
static void parameter_rows(Loop *loop, Sensitivity *s)
{
    const CoreCorrection *c = loop->plan->correction;
    for (size_t channel = 0; channel < c->n_channels; ++channel) {
        channel_row(loop, s, channel);
    }
    if (c->term_gate != 0.0 && c->n_channels == 1) {
        base_gradient(c, s->activations, s->input_gradient);
    }
}

/* dz_i/dx_j of the network's input i. */
static double input_slope(const CoreCorrection *c, const Sensitivity *s, size_t i, size_t j)
{
    int index = c->input_index[i];
    switch (c->input_source[i]) {
    case SOURCE_STATE:
        return (size_t)index == j ? 1.0 : 0.0;
    case SOURCE_DERIVATIVE:
        return s->J_fmu[(size_t)index * s->n + j];
    default:
        return s->dvars[(size_t)index * s->n + j];
    }
}

/* J = df/dx and F = df/dtheta at (t, x): the FMU by forward differences, the network through its
 * input gradient; f0 gets f(t, x). */
static int linearised(Loop *loop, Sensitivity *s, double t, const double *x)
{
    const CoreCorrection *c = loop->plan->correction;
    size_t n = s->n, m = c->n_variables;
    if (s->lin_valid && t == s->lin_t && memcmp(x, s->lin_x, n * sizeof(double)) == 0) {
        return 0;
    }
    s->lin_valid = 0;
    if (loop_derivatives(loop, t, x, s->f0)) {
        return 1;
    }
    memcpy(s->vars0, loop->variables, m * sizeof(double));
    memcpy(s->der0, s->f0, n * sizeof(double));
    for (size_t channel = 0; channel < c->n_channels; ++channel) {
        s->der0[c->channel_state[channel]] = loop->raw_channel[channel];
    }
    parameter_rows(loop, s);       /* uses raw_channel of this nominal evaluation */
    memcpy(s->xp, x, n * sizeof(double));
    for (size_t j = 0; j < n; ++j) {
        double step = fd_step(x[j]);
        s->xp[j] = x[j] + step;
        step = s->xp[j] - x[j];
        if (loop_fmu_values(loop, t, s->xp, s->fp, s->vars_p)) {
            return 1;
        }
        for (size_t i = 0; i < n; ++i) {
            s->J_fmu[i * n + j] = (s->fp[i] - s->der0[i]) / step;
        }
        for (size_t v = 0; v < m; ++v) {
            s->dvars[v * n + j] = (s->vars_p[v] - s->vars0[v]) / step;
        }
        s->xp[j] = x[j];
    }
    memcpy(s->J, s->J_fmu, n * n * sizeof(double));
    for (size_t channel = 0; channel < c->n_channels; ++channel) {
        size_t row = (size_t)c->channel_state[channel];
        const double *gradient = s->input_gradient + channel * c->n_inputs;
        for (size_t j = 0; j < n; ++j) {
            double sum = c->gate_fmu[channel] * s->J_fmu[row * n + j];
            for (size_t i = 0; i < c->n_inputs; ++i) {
                sum += gradient[i] * input_slope(c, s, i, j);
            }
            s->J[row * n + j] = sum;
        }
    }
    s->lin_t = t;
    memcpy(s->lin_x, x, n * sizeof(double));
    s->lin_valid = 1;
    return 0;
}

/* K = J S_stage + F (F on the channels' rows). */
static void stage_slope(const Loop *loop, Sensitivity *s, const double *S_stage, double *K)
{
    const CoreCorrection *c = loop->plan->correction;
    size_t n = s->n, P = s->P;
    for (size_t i = 0; i < n; ++i) {
        double *Ki = K + i * P;
        memset(Ki, 0, P * sizeof(double));
        for (size_t j = 0; j < n; ++j) {
            double a = s->J[i * n + j];
            if (a == 0.0) {
                continue;
            }
            const double *Sj = S_stage + j * P;
            for (size_t p = 0; p < P; ++p) {
                Ki[p] += a * Sj[p];
            }
        }
    }
    for (size_t channel = 0; channel < c->n_channels; ++channel) {
        double *Ki = K + (size_t)c->channel_state[channel] * P;
        const double *Fc = s->F + channel * P;
        for (size_t p = 0; p < P; ++p) {
            Ki[p] += Fc[p];
        }
    }
}

/* out = S + a K, over [n][P]. */
static void axpy_all(size_t count, const double *S, double a, const double *K, double *out)
{
    for (size_t i = 0; i < count; ++i) {
        out[i] = S[i] + a * K[i];
    }
}

static int sens_step(Loop *loop, double t, double h, const double *x)
{
    Sensitivity *s = loop->sens;
    if (s->weights == NULL) {
        return 0;
    }
    size_t n = s->n, count = n * s->P;
    double *S_new = s->S_prev;      /* S_prev is free: it becomes the old S below */
    if (loop->plan->solver == CORE_EULER) {
        if (linearised(loop, s, t, x)) {
            return 1;
        }
        stage_slope(loop, s, s->S, s->K);
        axpy_all(count, s->S, h, s->K, S_new);
    } else {
        /* RK4's stages, at the points the nominal step evaluated (its k1, k2, k3 give them) */
        const double *slopes[3] = {loop->dx_prev, loop->k2, loop->k3};
        const double fractions[4] = {0.0, 0.5, 0.5, 1.0}, weights[4] = {1.0, 2.0, 2.0, 1.0};
        for (int stage = 0; stage < 4; ++stage) {
            double fraction = fractions[stage];
            for (size_t i = 0; i < n; ++i) {
                s->xs[i] = stage == 0 ? x[i] : x[i] + (fraction * h) * slopes[stage - 1][i];
            }
            if (linearised(loop, s, stage == 0 ? t : stage == 3 ? t + h : t + 0.5 * h, s->xs)) {
                return 1;
            }
            stage_slope(loop, s, stage == 0 ? s->S : s->S_stage, s->K);
            /* one pass: the weighted sum of the stages' slopes and the next stage's sensitivities */
            double next = stage < 3 ? fractions[stage + 1] * h : 0.0, weight = weights[stage];
            for (size_t i = 0; i < count; ++i) {
                double k = s->K[i];
                s->K_sum[i] = stage == 0 ? k : s->K_sum[i] + weight * k;
                s->S_stage[i] = s->S[i] + next * k;
            }
        }
        axpy_all(count, s->S, h / 6.0, s->K_sum, S_new);
    }
    s->S_prev = s->S;
    s->S = S_new;
    s->st_prev = t;
    s->st = t + h;
    return 0;
}

/* S at t within the last step, linear between its ends, into out (or S itself at the end). */
static const double *sensitivity_at(Sensitivity *s, double t, double *out)
{
    if (t == s->st || s->st == s->st_prev) {
        return s->S;
    }
    double theta = (t - s->st_prev) / (s->st - s->st_prev);
    for (size_t i = 0; i < s->n * s->P; ++i) {
        out[i] = s->S_prev[i] + theta * (s->S[i] - s->S_prev[i]);
    }
    return out;
}

static void sens_restart(Loop *loop, double t)
{
    Sensitivity *s = loop->sens;
    if (s->weights == NULL) {
        return;
    }
    if (t != s->st) {
        const double *S = sensitivity_at(s, t, s->S_stage);
        if (S != s->S) {
            memcpy(s->S, S, s->n * s->P * sizeof(double));
        }
    }
    memcpy(s->S_prev, s->S, s->n * s->P * sizeof(double));
    s->st = s->st_prev = t;
}

static void sens_after_event(Loop *loop, int values_changed)
{
    loop->sens->lin_valid = 0;      /* the event may have changed the discrete states */
    loop->sens->resets += values_changed != 0;
}

/* v += w dy/dx for the computed columns, by forward differences. */
static int computed_rows(Loop *loop, Sensitivity *s, double t, const double *x, const double *w)
{
    const CorePlan *p = loop->plan;
    size_t n = s->n;
    if (loop_computed(loop, t, x)) {
        return 1;
    }
    memcpy(s->y0, loop->computed, p->n_computed * sizeof(double));
    memcpy(s->xp, x, n * sizeof(double));
    for (size_t j = 0; j < n; ++j) {
        double step = fd_step(x[j]);
        s->xp[j] = x[j] + step;
        step = s->xp[j] - x[j];
        if (loop_computed(loop, t, s->xp)) {
            return 1;
        }
        for (size_t col = 0; col < p->n_columns; ++col) {
            if (p->column_kind[col] == COLUMN_COMPUTED && w[col] != 0.0) {
                int index = p->column_index[col];
                s->v[j] += w[col] * (loop->computed[index] - s->y0[index]) / step;
            }
        }
        s->xp[j] = x[j];
    }
    return 0;
}

static int sens_record(Loop *loop, double t, const double *x, size_t row)
{
    Sensitivity *s = loop->sens;
    const CorePlan *p = loop->plan;
    if (s->weights == NULL || row >= s->n_outputs || !loop->continuous_mode) {
        return 0;
    }
    const double *w = s->weights + row * s->n_columns;
    size_t n = s->n, P = s->P;
    int derivative = 0, computed = 0;
    memset(s->v, 0, n * sizeof(double));
    for (size_t col = 0; col < p->n_columns; ++col) {
        if (w[col] == 0.0) {
            continue;
        }
        derivative |= p->column_kind[col] == COLUMN_DERIVATIVE;
        computed |= p->column_kind[col] == COLUMN_COMPUTED;
        if (p->column_kind[col] == COLUMN_STATE) {
            s->v[p->column_index[col]] += w[col];
        }
    }
    if (derivative) {       /* a corrected derivative: J S + F */
        const CoreCorrection *c = p->correction;
        if (linearised(loop, s, t, x)) {
            return 1;
        }
        for (size_t col = 0; col < p->n_columns; ++col) {
            if (p->column_kind[col] != COLUMN_DERIVATIVE || w[col] == 0.0) {
                continue;
            }
            int index = p->column_index[col];
            for (size_t j = 0; j < n; ++j) {
                s->v[j] += w[col] * s->J[index * n + j];
            }
            for (size_t channel = 0; channel < c->n_channels; ++channel) {
                if (c->channel_state[channel] == index) {
                    for (size_t q = 0; q < P; ++q) {
                        s->gradient[q] += w[col] * s->F[channel * P + q];
                    }
                }
            }
        }
    }
    if (computed && computed_rows(loop, s, t, x, w)) {
        return 1;
    }
    const double *S = sensitivity_at(s, t, s->K);
    for (size_t j = 0; j < n; ++j) {
        if (s->v[j] == 0.0) {
            continue;
        }
        const double *Sj = S + j * P;
        for (size_t q = 0; q < P; ++q) {
            s->gradient[q] += s->v[j] * Sj[q];
        }
    }
    return 0;
}

int core_gradient_run(const CoreFmu *fmu, const CorePlan *plan, const double *weights, size_t n_rows,
                      size_t n_parameters, double *gradient, int64_t *resets, CoreResult *result)
{
    const CoreCorrection *c = plan->correction;
    size_t n = plan->n_states, P = n_parameters, width_total = 0, widest = 0;
    for (size_t l = 0; c != NULL && l < c->n_layers; ++l) {
        size_t rows = (size_t)c->layer_rows[l];
        width_total += rows;
        widest = rows > widest ? rows : widest;
    }
    Sensitivity s;
    memset(&s, 0, sizeof(s));
    s.n = n;
    s.P = P;
    s.n_columns = plan->n_columns;
    s.n_outputs = n_rows;
    s.weights = c != NULL && c->n_layers > 0 ? weights : NULL;
    s.gradient = gradient;
    size_t n_inputs = c != NULL ? c->n_inputs : 0;
    s.width_total = n_inputs + width_total;
    size_t matrices = 6 * n * P + (c != NULL ? c->n_channels : 0) * P;
    size_t n_channels = c != NULL ? c->n_channels : 0, m = c != NULL ? c->n_variables : 0;
    size_t words = matrices + 2 * n * n + 7 * n + s.width_total + 2 * (widest + n_inputs)
                   + n_channels * n_inputs + 2 * m + m * n + plan->n_computed + 1;
    double *memory = s.weights != NULL ? calloc(words, sizeof(double)) : NULL;
    if (s.weights != NULL && memory == NULL) {
        memset(result, 0, sizeof(*result));
        result->error = CORE_NO_MEMORY;
        return result->error;
    }
    if (memory != NULL) {
        double *pool = memory;
        double **matrix[] = {&s.S, &s.S_prev, &s.S_stage, &s.K, &s.K_sum};
        for (size_t k = 0; k < 5; ++k) {
            *matrix[k] = pool;
            pool += n * P;
        }
        pool += n * P;          /* room for sensitivity_at's interpolation in K's place */
        s.F = pool;
        pool += c->n_channels * P;
        s.J = pool;
        pool += n * n;
        double **vectors[] = {&s.f0, &s.fp, &s.xp, &s.xs, &s.v, &s.lin_x};
        for (size_t k = 0; k < 6; ++k) {
            *vectors[k] = pool;
            pool += n;
        }
        s.activations = pool;
        pool += s.width_total;
        s.delta = pool;
        pool += widest + n_inputs;
        s.delta_next = pool;
        pool += widest + n_inputs;
        s.input_gradient = pool;
        pool += n_channels * n_inputs;
        s.der0 = pool;
        pool += n;
        s.J_fmu = pool;
        pool += n * n;
        s.vars0 = pool;
        pool += m;
        s.vars_p = pool;
        pool += m;
        s.dvars = pool;
        pool += m * n;
        s.y0 = pool;
        s.st = s.st_prev = plan->start;
        memset(gradient, 0, P * sizeof(double));
    }
    SensitivityHooks hooks = {&s, s.weights != NULL ? s.activations : NULL, sens_step, sens_restart, sens_record,
                              sens_after_event};
    int code = loop_run(fmu, plan, result, &hooks);
    *resets = s.resets;
    free(memory);
    return code;
}
