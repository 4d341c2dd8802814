/* The per-step numerical kernels of DroneAgent, compiled (issue 16).
 *
 * Pure arithmetic on caller-owned float64 buffers: no state, no allocation, no I/O. Each
 * function is the same formula as a readable numpy form in swarm.core, which the tests bind
 * it to (tests/core/test_kernels.py: parity on random states in every regime, finite
 * differences of the gradients, the singular fallback):
 *
 *   perception        perception.perception_terms                     SPEC §3, thesis 3.6-3.7
 *   symmetric_eigen   np.linalg.eigh of a 3x3 (ascending, columns)
 *   smooth_min        smooth_min.smooth_min_eigenvalue's coefficients SPEC §7
 *   perception_barrier  the above, then barrier.localization_barrier   SPEC §8, 3.20-3.25, 3.32
 *                     for M targets in one call (what the agent runs)
 *   filter_stack      icf.posterior, posterior_covariance and predict  SPEC §5, 2.8-2.11
 *                     for M targets (n = 3 or 6)
 *   qp_rows           the local QP's rows: barrier.weight_sum_row,             SPEC §8
 *                     collision_row and robust_lower_bound after the localization 3.32-3.36
 *                     rows, then the envelope's (DroneAgent's assembly)           4.1-4.2
 *   qp_load           the local QP (3.36-3.37) of one solve written into the     SPEC §9
 *                     workspace's arrays, as qp.build_local_qp assembles it
 *   qp_max_violation  qp.LocalQp.max_violation of the local QP (3.36-3.37), SPEC §9
 *                     from its row inputs (LocalQpWorkspace's feasibility checks)
 *   initial_information  icf.initial_information for M targets from the measured  SPEC §4-§5
 *                     image points (projector.bearing_from_image_point)          2.4-2.5, 2.15
 *   consensus_sums    icf.consensus_iteration of the packed ICF pair, and the    SPEC §5-§6
 *                     disagreement of the round-0 consensus states (DroneAgent)  2.6-2.7
 *   consensus_step    the packed PI consensus and Gramian step, drone_step._consensus_operator
 *                     (pi_consensus_step, gramian_step)                          3.29-3.30
 *
 * The layouts of what they write and read and the order of the constants they take are
 * stated once, here, and exported by the module (../compiled.h): ROW_FIELDS and
 * SMOOTH_MIN_FIELDS (output rows), PERCEPTION_CONSTANTS, BARRIER_CONSTANTS, QP_ROW_CONSTANTS
 * and LOCALIZATION_SHARES (constants), ICF_PAIR and CONSENSUS_STEP_Z (packed vectors).
 * swarm.core.kernels reads them; Python writes no offset of its own.
 *
 * Why hand-written Cholesky and Jacobi: LAPACK from C would have to come from scipy (its
 * cython_lapack capsules), whose import costs each agent ~0.3 s of the 2 s launch budget, and
 * numpy does not export its LAPACK. At these fixed sizes (3x3, 6x6) a Cholesky factorization
 * and a cyclic Jacobi eigensolver are a few lines each, and the tests hold them to LAPACK's
 * results (numpy) to round-off.
 */
#include "../compiled.h"
#include <math.h>

#define MAX_STATE 6

/* -- perception (SPEC §3) ------------------------------------------------------------------ */

/* Perception constants, in this order; exported as PERCEPTION_CONSTANTS, named as
 * params.PerceptionParams names them. */
enum { K_DMIN, K_DMAX, K_SDMIN, K_SDMAX, K_COS, K_SBETA, N_PERCEPTION_CONSTANTS };
static const char *const perception_constant_names[N_PERCEPTION_CONSTANTS] = {
    [K_DMIN] = "d_min_th_m", [K_DMAX] = "d_max_th_m", [K_SDMIN] = "sigma_dmin_sq_m2",
    [K_SDMAX] = "sigma_dmax_sq_m2", [K_COS] = "cos_alpha_th", [K_SBETA] = "sigma_beta_sq"};

/* Output of one drone-target pair: w, ∂w/∂p_i (3), β̂ (3), d̂, Π̂ row-major (9); exported
 * with the barrier's as ROW_FIELDS (row_fields below). */
enum { P_WEIGHT = 0, P_GRAD = 1, P_UNIT = 4, P_DISTANCE = 7, P_PROJECTOR = 8, N_PERCEPTION = 17 };

static void
perception(const double drone[3], const double target[3], const double k[6], double out[17])
{
    double rx = target[0] - drone[0], ry = target[1] - drone[1], rz = target[2] - drone[2];
    double distance = sqrt(rx * rx + ry * ry + rz * rz);
    double bx = rx / distance, by = ry / distance, bz = rz / distance;
    /* Π̂ = I − β̂β̂ᵀ, symmetric: 0.0 − x as the Python form (its sign of zero). */
    double pxy = 0.0 - bx * by, pxz = 0.0 - bx * bz, pyz = 0.0 - by * bz;
    double *proj = out + P_PROJECTOR;
    proj[0] = 1.0 - bx * bx; proj[1] = pxy; proj[2] = pxz;
    proj[3] = pxy; proj[4] = 1.0 - by * by; proj[5] = pyz;
    proj[6] = pxz; proj[7] = pyz; proj[8] = 1.0 - bz * bz;
    double w_d, dw_d, w_b, dw_b, gap;
    if (distance < k[K_DMIN]) {
        gap = distance - k[K_DMIN];
        w_d = exp(-gap * gap / k[K_SDMIN]);
        dw_d = -2.0 * gap / k[K_SDMIN] * w_d;
    } else if (distance > k[K_DMAX]) {
        gap = distance - k[K_DMAX];
        w_d = exp(-gap * gap / k[K_SDMAX]);
        dw_d = -2.0 * gap / k[K_SDMAX] * w_d;
    } else {
        w_d = 1.0; dw_d = 0.0;
    }
    double cos_off_axis = -bz;
    if (cos_off_axis < k[K_COS]) {
        gap = cos_off_axis - k[K_COS];
        w_b = exp(-gap * gap / k[K_SBETA]);
        dw_b = -2.0 * gap / k[K_SBETA] * w_b;
    } else {
        w_b = 1.0; dw_b = 0.0;
    }
    /* ∂w/∂p_i = −w_β w_D' β̂ + (w_D w_β'/d̂) Π̂ e_3 (∂d̂/∂p_i = −β̂ᵀ, ∂c/∂p_i = e_3ᵀΠ̂/d̂). */
    double a = -(w_b * dw_d), c = w_d * dw_b / distance;
    out[P_WEIGHT] = w_d * w_b;
    out[P_GRAD] = a * bx + c * pxz;
    out[P_GRAD + 1] = a * by + c * pyz;
    out[P_GRAD + 2] = a * bz + c * proj[8];
    out[P_UNIT] = bx; out[P_UNIT + 1] = by; out[P_UNIT + 2] = bz;
    out[P_DISTANCE] = distance;
}

/* -- 3x3 symmetric eigen-decomposition ----------------------------------------------------- */

/* Cyclic Jacobi: rotations zero each off-diagonal entry in turn until none is left above
 * round-off of the diagonal. Eigenvalues ascending, eigenvectors as the columns of v
 * (row-major), as np.linalg.eigh returns them. Returns 0, or -1 if an entry is not finite
 * or the sweeps do not converge. */
static int
symmetric_eigen(const double matrix[9], double values[3], double v[9])
{
    double a[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            a[i][j] = matrix[3 * i + j];
            if (!isfinite(a[i][j])) return -1;
        }
    double q[3][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
    static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    int converged = 0;
    for (int sweep = 0; sweep < 50 && !converged; sweep++) {
        converged = 1;
        for (int t = 0; t < 3; t++) {
            int p = pairs[t][0], r = pairs[t][1];
            double apr = a[p][r];
            if (apr == 0.0) continue;
            /* Negligible against both diagonal entries: zero it (the classic test). */
            if (fabs(apr) <= 1e-18 * fabs(a[p][p]) && fabs(apr) <= 1e-18 * fabs(a[r][r])) {
                a[p][r] = a[r][p] = 0.0;
                continue;
            }
            converged = 0;
            double theta = (a[r][r] - a[p][p]) / (2.0 * apr);
            double tan_ = (theta >= 0.0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
            double cos_ = 1.0 / sqrt(tan_ * tan_ + 1.0), sin_ = tan_ * cos_;
            /* a ← Jᵀ a J with J the rotation in the (p, r) plane; q ← q J. */
            for (int k = 0; k < 3; k++) {
                double akp = a[k][p], akr = a[k][r];
                a[k][p] = cos_ * akp - sin_ * akr;
                a[k][r] = sin_ * akp + cos_ * akr;
            }
            for (int k = 0; k < 3; k++) {
                double apk = a[p][k], ark = a[r][k];
                a[p][k] = cos_ * apk - sin_ * ark;
                a[r][k] = sin_ * apk + cos_ * ark;
            }
            a[p][r] = a[r][p] = 0.0;
            for (int k = 0; k < 3; k++) {
                double qkp = q[k][p], qkr = q[k][r];
                q[k][p] = cos_ * qkp - sin_ * qkr;
                q[k][r] = sin_ * qkp + cos_ * qkr;
            }
        }
    }
    if (!converged) return -1;
    int order[3] = {0, 1, 2};
    for (int i = 1; i < 3; i++)
        for (int j = i; j > 0 && a[order[j]][order[j]] < a[order[j - 1]][order[j - 1]]; j--) {
            int s = order[j]; order[j] = order[j - 1]; order[j - 1] = s;
        }
    for (int c = 0; c < 3; c++) {
        values[c] = a[order[c]][order[c]];
        for (int k = 0; k < 3; k++) v[3 * k + c] = q[k][order[c]];
    }
    return 0;
}

/* -- smooth minimum eigenvalue (SPEC §7) --------------------------------------------------- */

typedef struct {
    double floor;     /* smooth_min.EIGENVALUE_FLOOR */
    double log_gap;   /* smooth_min.NEAR_REPEATED_LOG_GAP */
} SmoothMinLimits;

/* θ_kl = (g_k − g_l)/(λ_k − λ_l), or for nearly repeated eigenvalues
 * g_l/λ_l · expm1((p−1)t)/expm1(t), t = log(λ_k/λ_l) (smooth_min.divided_difference). */
static double
divided_difference(double lam_k, double lam_l, double g_k, double g_l, double p, double log_gap)
{
    double t = log(lam_k / lam_l);
    if (fabs(t) >= log_gap) return (g_k - g_l) / (lam_k - lam_l);
    double ratio = t == 0.0 ? p - 1.0 : expm1((p - 1.0) * t) / expm1(t);
    return g_l / lam_l * ratio;
}

/* Output: λ̄, λ clipped (3), g (3), ∂²f/∂λ∂λ as h00 h11 h22 h01 h02 h12, θ01 θ02 θ12;
 * exported as SMOOTH_MIN_FIELDS. */
enum { S_VALUE = 0, S_LAMBDA = 1, S_GRAD = 4, S_HESS = 7, S_THETA = 13, N_SMOOTH = 16 };
static const Field smooth_min_fields[] = {
    {"value", S_VALUE}, {"eigenvalues", S_LAMBDA}, {"eigen_gradient", S_GRAD},
    {"eigen_hessian", S_HESS}, {"divided_differences", S_THETA}};

static void
smooth_min(const double raw[3], double p, SmoothMinLimits lim, double out[16])
{
    double l0 = raw[0] > lim.floor ? raw[0] : lim.floor;
    double l1 = raw[1] > lim.floor ? raw[1] : lim.floor;
    double l2 = raw[2] > lim.floor ? raw[2] : lim.floor;
    double value = l0 * pow(pow(l0 / l0, p) + pow(l1 / l0, p) + pow(l2 / l0, p), 1.0 / p);
    double pm1 = p - 1.0, one_minus_p = 1.0 - p;
    double g0 = pow(l0 / value, pm1), g1 = pow(l1 / value, pm1), g2 = pow(l2 / value, pm1);
    out[S_VALUE] = value;
    out[S_LAMBDA] = l0; out[S_LAMBDA + 1] = l1; out[S_LAMBDA + 2] = l2;
    out[S_GRAD] = g0; out[S_GRAD + 1] = g1; out[S_GRAD + 2] = g2;
    out[S_HESS] = one_minus_p * (g0 * g0) / value + pm1 * g0 / l0;
    out[S_HESS + 1] = one_minus_p * (g1 * g1) / value + pm1 * g1 / l1;
    out[S_HESS + 2] = one_minus_p * (g2 * g2) / value + pm1 * g2 / l2;
    out[S_HESS + 3] = one_minus_p * (g0 * g1) / value;
    out[S_HESS + 4] = one_minus_p * (g0 * g2) / value;
    out[S_HESS + 5] = one_minus_p * (g1 * g2) / value;
    out[S_THETA] = divided_difference(l0, l1, g0, g1, p, lim.log_gap);
    out[S_THETA + 1] = divided_difference(l0, l2, g0, g2, p, lim.log_gap);
    out[S_THETA + 2] = divided_difference(l1, l2, g1, g2, p, lim.log_gap);
}

/* -- the localization barrier (SPEC §8) ---------------------------------------------------- */

typedef struct {
    double n_agents, forgetting, epsilon, exponent, info_gain;
} BarrierConstants;

/* Output: λ̄, ψ0, ψ1, L_gi ψ1 (3), lower bound −(c + ψ1)/N − d_i. */
enum { B_LAMBDA = 0, B_PSI0 = 1, B_PSI1 = 2, B_LIE = 3, B_LOWER = 6, N_BARRIER = 7 };

/* A row of perception_barrier: the pair's perception terms, then the target's barrier terms;
 * exported as ROW_FIELDS, named as kernels.PerceptionScalars and BarrierScalars name them. */
static const Field row_fields[] = {
    {"weight", P_WEIGHT}, {"weight_grad_drone", P_GRAD}, {"unit_bearing", P_UNIT},
    {"distance_m", P_DISTANCE}, {"projector", P_PROJECTOR},
    {"lambda_bar", N_PERCEPTION + B_LAMBDA}, {"psi0", N_PERCEPTION + B_PSI0},
    {"psi1", N_PERCEPTION + B_PSI1}, {"lie_g", N_PERCEPTION + B_LIE},
    {"lower_bound", N_PERCEPTION + B_LOWER}};

/* barrier.localization_barrier evaluated in the eigenbasis of G, where Γ = V diag(g) Vᵀ is
 * never formed: H̃ = VᵀĠV = −ρ diag(λ) + bN VᵀsV, ⟨Γ, Ġ⟩ = Σ g_k H̃_kk, with c_k = v_k·β̂:
 * ⟨Γ, Π̂⟩ = Σ g_k − β̂ᵀΓβ̂ and ⟨Γ, ∂Π̂/∂p_i,k⟩ = (2/d̂)(Π̂Γβ̂)_k (B.15). */
static void
localization_barrier(const double raw[3], const double v[9], const double s[9],
                     const double terms[17], const double velocity[3], BarrierConstants b,
                     SmoothMinLimits lim, double out[7])
{
    double sm[N_SMOOTH];
    smooth_min(raw, b.exponent, lim, sm);
    const double g0 = sm[S_GRAD], g1 = sm[S_GRAD + 1], g2 = sm[S_GRAD + 2];
    /* q = s V (column l: s v_l), then the entries of H̃ with k ≤ l. */
    double q[9];
    for (int i = 0; i < 3; i++)
        for (int l = 0; l < 3; l++)
            q[3 * i + l] = s[3 * i] * v[l] + s[3 * i + 1] * v[3 + l] + s[3 * i + 2] * v[6 + l];
#define VQ(k, l) (v[k] * q[l] + v[3 + k] * q[3 + l] + v[6 + k] * q[6 + l])
    double neg_rho = -b.forgetting, bn = b.info_gain * b.n_agents;
    double d0 = neg_rho * raw[0] + bn * VQ(0, 0);
    double d1 = neg_rho * raw[1] + bn * VQ(1, 1);
    double d2 = neg_rho * raw[2] + bn * VQ(2, 2);
    double o01 = bn * VQ(0, 1), o02 = bn * VQ(0, 2), o12 = bn * VQ(1, 2);
#undef VQ
    double along_rate = g0 * d0 + g1 * d1 + g2 * d2;  /* ⟨Γ, Ġ⟩ */
    double psi0 = sm[S_VALUE] - b.epsilon;
    double psi1 = along_rate + psi0;
    /* L_gi ψ1 = b[∂w/∂p_i,k ⟨Γ, Π̂⟩ + (2w/d̂)(Π̂Γβ̂)_k]. */
    double weight = terms[P_WEIGHT], distance = terms[P_DISTANCE];
    const double *grad = terms + P_GRAD, *unit = terms + P_UNIT;
    double c0 = v[0] * unit[0] + v[3] * unit[1] + v[6] * unit[2];
    double c1 = v[1] * unit[0] + v[4] * unit[1] + v[7] * unit[2];
    double c2 = v[2] * unit[0] + v[5] * unit[1] + v[8] * unit[2];
    double gc0 = g0 * c0, gc1 = g1 * c1, gc2 = g2 * c2;
    double beta_gamma_beta = gc0 * c0 + gc1 * c1 + gc2 * c2;
    double gamma_proj = (g0 + g1 + g2) - beta_gamma_beta;
    double scale = 2.0 * weight / distance;
    double lie[3];
    for (int k = 0; k < 3; k++)
        lie[k] = b.info_gain * (grad[k] * gamma_proj
                                + scale * (v[3 * k] * gc0 + v[3 * k + 1] * gc1
                                           + v[3 * k + 2] * gc2 - unit[k] * beta_gamma_beta));
    double drift = -(lie[0] * velocity[0] + lie[1] * velocity[1] + lie[2] * velocity[2]);
    /* D²λ̄[Ġ, Ġ] (SPEC §7). */
    const double *h = sm + S_HESS, *theta = sm + S_THETA;
    double second = (h[0] * d0 * d0 + h[1] * d1 * d1 + h[2] * d2 * d2
                     + 2.0 * (h[3] * d0 * d1 + h[4] * d0 * d2 + h[5] * d1 * d2)
                     + 2.0 * (theta[0] * o01 * o01 + theta[1] * o02 * o02
                              + theta[2] * o12 * o12));
    double coupling = second + (1.0 - b.forgetting) * along_rate;
    out[B_LAMBDA] = sm[S_VALUE];
    out[B_PSI0] = psi0;
    out[B_PSI1] = psi1;
    out[B_LIE] = lie[0]; out[B_LIE + 1] = lie[1]; out[B_LIE + 2] = lie[2];
    out[B_LOWER] = -(coupling + psi1) / b.n_agents - drift;
}

/* -- the ICF's local steps (SPEC §5) ------------------------------------------------------- */

/* Lower Cholesky factor of the n×n row-major a into l; 0 if every pivot is positive and every
 * entry finite (np.linalg.cholesky succeeds), -1 otherwise. */
static int
cholesky(const double *a, int n, double *l)
{
    for (int i = 0; i < n; i++) {
        for (int j = 0; j <= i; j++) {
            double sum = a[n * i + j];
            for (int k = 0; k < j; k++) sum -= l[n * i + k] * l[n * j + k];
            if (i == j) {
                if (!(sum > 0.0) || !isfinite(sum)) return -1;
                l[n * i + i] = sqrt(sum);
            } else {
                l[n * i + j] = sum / l[n * j + j];
                if (!isfinite(l[n * i + j])) return -1;
            }
        }
        for (int j = i + 1; j < n; j++) l[n * i + j] = 0.0;
    }
    return 0;
}

/* a⁻¹ = L⁻ᵀL⁻¹ from the Cholesky factor l, symmetric exactly (one triangle mirrored). */
static void
inverse_from_cholesky(const double *l, int n, double *inv)
{
    double li[MAX_STATE * MAX_STATE] = {0};  /* L⁻¹, lower triangular */
    for (int j = 0; j < n; j++) {
        li[n * j + j] = 1.0 / l[n * j + j];
        for (int i = j + 1; i < n; i++) {
            double sum = 0.0;
            for (int k = j; k < i; k++) sum -= l[n * i + k] * li[n * k + j];
            li[n * i + j] = sum / l[n * i + i];
        }
    }
    for (int i = 0; i < n; i++)
        for (int j = 0; j <= i; j++) {
            double sum = 0.0;
            for (int k = i; k < n; k++) sum += li[n * k + i] * li[n * k + j];
            inv[n * i + j] = inv[n * j + i] = sum;
        }
}

/* x̂⁺ = V⁻¹v, P⁺ = V⁻¹/N (= pinv(W⁺), W⁺ = NV), W⁻ = (A P⁺ Aᵀ + qI)⁻¹, x̂⁻ = A x̂⁺ (2.8-2.11)
 * for each of the m targets. Returns 0, or -1 if some V or A P⁺ Aᵀ + qI is not positive
 * definite (the caller then takes the pseudo-inverse path). */
static int
filter_stack(const double *information, const double *vector, const double *transition,
             int m, int n, double process_noise, double n_agents, double *posterior_state,
             double *prior_state, double *prior_information, double *posterior_covariance)
{
    double factor[MAX_STATE * MAX_STATE], inv[MAX_STATE * MAX_STATE];
    double ap[MAX_STATE * MAX_STATE], cov[MAX_STATE * MAX_STATE];
    const double *a = transition;
    for (int r = 0; r < m; r++) {
        const double *info = information + (size_t)r * n * n, *vec = vector + (size_t)r * n;
        if (cholesky(info, n, factor) != 0) return -1;
        inverse_from_cholesky(factor, n, inv);
        double *x = posterior_state + (size_t)r * n, *pc = posterior_covariance + (size_t)r * n * n;
        for (int i = 0; i < n; i++) {
            double sum = 0.0;
            for (int k = 0; k < n; k++) sum += inv[n * i + k] * vec[k];
            x[i] = sum;
        }
        for (int i = 0; i < n * n; i++) pc[i] = inv[i] / n_agents;
        for (int i = 0; i < n; i++)          /* A P⁺ */
            for (int j = 0; j < n; j++) {
                double sum = 0.0;
                for (int k = 0; k < n; k++) sum += a[n * i + k] * pc[n * k + j];
                ap[n * i + j] = sum;
            }
        for (int i = 0; i < n; i++)          /* (A P⁺) Aᵀ + qI, one triangle mirrored */
            for (int j = 0; j <= i; j++) {
                double sum = 0.0;
                for (int k = 0; k < n; k++) sum += ap[n * i + k] * a[n * j + k];
                cov[n * i + j] = cov[n * j + i] = sum;
            }
        for (int i = 0; i < n; i++) cov[n * i + i] += process_noise;
        if (cholesky(cov, n, factor) != 0) return -1;
        inverse_from_cholesky(factor, n, prior_information + (size_t)r * n * n);
        double *xp = prior_state + (size_t)r * n;
        for (int i = 0; i < n; i++) {
            double sum = 0.0;
            for (int k = 0; k < n; k++) sum += a[n * i + k] * x[k];
            xp[i] = sum;
        }
    }
    return 0;
}

/* The local QP of one solve into LocalQpWorkspace's arrays (SPEC §9, 3.36-3.37), entry for
 * entry as qp.build_local_qp assembles it: the u columns of the R rows (columns: every row's
 * x, then y, then z) into rows (R x n_z, C order; the slack columns are left as they are),
 * the rows' lower bounds after the n_z bounds of z in bounds_lower, the box of u into the
 * first 3 entries of bounds_lower and bounds_upper, q = -2 u_d into linear[:3] and, for the
 * relaxed QP (n_z = 3 + 2M), the slack penalties 2 K max(w_r, w_floor) of delta_r and
 * delta_w_r into P's diagonal. Returns whether P changed. */
static int
qp_load(const double *columns, const double *lower, Py_ssize_t n_rows, const double nominal[3],
        const double low[3], const double high[3], const double *weights, double slack_weight,
        double weight_floor, Py_ssize_t n_z, double *rows, double *bounds_lower,
        double *bounds_upper, double *linear, double *hessian)
{
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        double *row = rows + r * n_z;
        row[0] = columns[r];
        row[1] = columns[n_rows + r];
        row[2] = columns[2 * n_rows + r];
        bounds_lower[n_z + r] = lower[r];
    }
    for (int k = 0; k < 3; k++) {
        bounds_lower[k] = low[k];
        bounds_upper[k] = high[k];
        linear[k] = -2.0 * nominal[k];
    }
    int changed = 0;
    Py_ssize_t m = (n_z - 3) / 2;
    for (Py_ssize_t r = 0; r < m; r++) {
        /* max(w, floor) as Python's max: floor only when it is larger (a NaN w stays) */
        double penalty = 2.0 * slack_weight * (weight_floor > weights[r] ? weight_floor
                                                                          : weights[r]);
        double *first = hessian + (3 + r) * (n_z + 1), *second = hessian + (3 + m + r) * (n_z + 1);
        if (*first != penalty || *second != penalty) {
            *first = *second = penalty;
            changed = 1;
        }
    }
    return changed;
}

/* -- feasibility of the local QP (SPEC §9) ------------------------------------------------- */

/* The largest violation of the local QP at z = [u (3), slacks (n_z - 3)]: of each row
 * a_r . u + delta_r >= lower_r (a_r: columns[r], columns[R + r], columns[2R + r]; delta_r =
 * z[3 + r] for the rows that have a slack, 0 for the others), of the box low <= u <= high and
 * of delta >= 0; 0 if none is violated. A NaN row gap is returned as it is (a NaN in z or in
 * the inputs is never feasible); NaNs elsewhere are skipped, as Python's max skips them. */
static double
qp_max_violation(const double *z, Py_ssize_t n_z, const double *columns, const double *lower,
                 Py_ssize_t n_rows, const double low[3], const double high[3])
{
    double worst = 0.0;
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        double slack = 3 + r < n_z ? z[3 + r] : 0.0;
        double gap = lower[r] - (columns[r] * z[0] + columns[n_rows + r] * z[1]
                                 + columns[2 * n_rows + r] * z[2] + slack);
        if (!(gap <= worst)) {
            if (gap != gap) return gap;
            worst = gap;
        }
    }
    for (int k = 0; k < 3; k++) {
        double below = low[k] - z[k], above = z[k] - high[k];
        if (below > worst) worst = below;
        if (above > worst) worst = above;
    }
    for (Py_ssize_t i = 3; i < n_z; i++)
        if (0.0 - z[i] > worst) worst = 0.0 - z[i];
    return worst;
}

/* -- the ICF's local step (SPEC §4-§5) -------------------------------------------------------- */

/* The packed ICF pair that initial_information writes (and consensus_sums takes as one vector
 * of floats): its parts in this order, exported as ICF_PAIR. */
enum { I_INFORMATION, I_VECTOR, N_PAIR_PARTS };
static const char *const pair_part_names[N_PAIR_PARTS] = {
    [I_INFORMATION] = "information", [I_VECTOR] = "information_vector"};

/* V0 = W/N + b[[P, 0], [0, 0]] into information (M n n) and v0 = W x / N + b[P p; 0] into
 * vectors (M n) (2.4-2.5, 2.15) for M targets, from the prior information W (M n n) and state
 * x (M n). P is the projector of the measured bearing [x_img, y_img, -1]/norm of target r's
 * image point; a target with detected[r] == 0 adds nothing (mu = 0). p: where the image was
 * taken. */
static void
initial_information(const double *prior_information, const double *prior_state, int m, int n,
                    double n_agents, double gain, const double p[3], const double *image_points,
                    const double *detected, double *information, double *vectors)
{
    for (int r = 0; r < m; r++) {
        const double *w = prior_information + (size_t)r * n * n, *x = prior_state + (size_t)r * n;
        double *info = information + (size_t)r * n * n, *v = vectors + (size_t)r * n;
        for (int i = 0; i < n * n; i++) info[i] = w[i] / n_agents;
        for (int i = 0; i < n; i++) {
            double sum = 0.0;
            for (int k = 0; k < n; k++) sum += info[n * i + k] * x[k];
            v[i] = sum;
        }
        if (!detected[r]) continue;
        double ix = image_points[2 * r], iy = image_points[2 * r + 1];
        double norm = sqrt(ix * ix + iy * iy + 1.0);
        double bx = ix / norm, by = iy / norm, bz = -1.0 / norm;
        double pxy = 0.0 - bx * by, pxz = 0.0 - bx * bz, pyz = 0.0 - by * bz;
        double proj[9] = {1.0 - bx * bx, pxy, pxz, pxy, 1.0 - by * by, pyz, pxz, pyz,
                          1.0 - bz * bz};
        for (int a = 0; a < 3; a++) {
            for (int b = 0; b < 3; b++) info[n * a + b] += gain * proj[3 * a + b];
            v[a] += gain * (proj[3 * a] * p[0] + proj[3 * a + 1] * p[1] + proj[3 * a + 2] * p[2]);
        }
    }
}

/* -- consensus (SPEC §5-§6) ------------------------------------------------------------------ */

static int
all_finite(const double *values, Py_ssize_t count)
{
    for (Py_ssize_t i = 0; i < count; i++)
        if (!isfinite(values[i])) return 0;
    return 1;
}

/* One ICF consensus iteration (2.6-2.7) on the packed pair a (n_icf floats): icf_out =
 * a + sum_j w_j (a_j - a), the neighbours in order, each difference rounded, then weighted,
 * then added, as consensus_iteration adds them; and with the round-0 states c (n_cons floats,
 * own_cons != NULL) disagreement_out = -sum_j (c_j - c). Neighbour j's block is [a_j | c_j].
 * The caller has dropped the blocks with a non-finite value. */
static void
consensus_sums(const double *own_icf, Py_ssize_t n_icf, const double *own_cons,
               Py_ssize_t n_cons, const double *const *blocks, const double *weights,
               Py_ssize_t count, double *icf_out, double *disagreement_out)
{
    for (Py_ssize_t i = 0; i < n_icf; i++) {
        double own = own_icf[i], sum = own;
        for (Py_ssize_t j = 0; j < count; j++) sum = sum + weights[j] * (blocks[j][i] - own);
        icf_out[i] = sum;
    }
    if (own_cons == NULL) return;
    for (Py_ssize_t i = 0; i < n_cons; i++) {
        double own = own_cons[i], sum = 0.0;
        for (Py_ssize_t j = 0; j < count; j++) {
            double difference = blocks[j][n_icf + i] - own;
            sum = j == 0 ? difference : sum + difference;
        }
        disagreement_out[i] = -sum;
    }
}

/* The vector z that consensus_step's index points into: its parts in this order (the state
 * x (n), the disagreement d (n), the local input u, one 0), exported as CONSENSUS_STEP_Z. */
enum { Z_STATE, Z_DISAGREEMENT, Z_INPUT, Z_ZERO, N_Z_PARTS };
static const char *const z_part_names[N_Z_PARTS] = {
    [Z_STATE] = "state", [Z_DISAGREEMENT] = "disagreement", [Z_INPUT] = "input",
    [Z_ZERO] = "zero"};

/* The packed consensus step: out[i] = sum_r coefficients[r][i] * z[index[r][i]] over the
 * `rows` terms in order (products rounded, then added from r = 0): what
 * np.add.reduce(z[index] * coefficients, axis=0) computes. */
static void
consensus_step(const double *z, Py_ssize_t n, const Py_ssize_t *index,
               const double *coefficients, Py_ssize_t rows, double *out)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        double sum = 0.0;
        for (Py_ssize_t r = 0; r < rows; r++) {
            double term = coefficients[r * n + i] * z[index[r * n + i]];
            sum = r == 0 ? term : sum + term;
        }
        out[i] = sum;
    }
}

/* -- Python glue --------------------------------------------------------------------------- */

static void
release(Py_buffer *views, int count)
{
    for (int i = 0; i < count; i++) PyBuffer_Release(&views[i]);
}

/* One argument of a kernel: which of the call's arguments, its name, its length in float64
 * items (-1: any, checked by the caller once the sizes are known) and whether the kernel
 * writes it. */
typedef struct {
    int arg;
    const char *name;
    Py_ssize_t length;
    int writable;
} BufferSpec;

/* Whether each of the `count` acquired views holds its expected number of float64 items;
 * if not, the error names the first that does not, and every view is released. */
static int
check_lengths(Py_buffer *views, const BufferSpec *specs, const Py_ssize_t *lengths, int count)
{
    for (int i = 0; i < count; i++)
        if (views[i].len / 8 != lengths[i]) {
            length_error(&views[i], lengths[i], specs[i].name);
            release(views, count);
            return -1;
        }
    return 0;
}

/* The buffers of `count` specs into views; on failure none is held and the error is set. */
static int
acquire(PyObject *const *args, const BufferSpec *specs, int count, Py_buffer *views)
{
    for (int i = 0; i < count; i++)
        if (float64_buffer(args[specs[i].arg], &views[i], specs[i].writable, specs[i].length,
                           specs[i].name)) {
            release(views, i);
            return -1;
        }
    return 0;
}

PyDoc_STRVAR(perception_doc,
"perception(drone, target, constants, out)\n--\n\n"
"w, dw/dp_i (3), unit bearing (3), distance, projector row-major (9) of one drone-target\n"
"pair into out (17, ROW_FIELDS): perception.perception_terms. constants: PERCEPTION_CONSTANTS.");

static PyObject *
py_perception(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const BufferSpec specs[4] = {{0, "drone", 3, 0}, {1, "target", 3, 0},
                                        {2, "constants", N_PERCEPTION_CONSTANTS, 0},
                                        {3, "out", N_PERCEPTION, 1}};
    Py_buffer v[4];
    if (check_nargs(nargs, 4, "perception") || acquire(args, specs, 4, v)) return NULL;
    perception(v[0].buf, v[1].buf, v[2].buf, v[3].buf);
    release(v, 4);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(symmetric_eigen_doc,
"symmetric_eigen(matrix, values, vectors) -> bool\n--\n\n"
"Eigenvalues (ascending, into values (3)) and eigenvectors (columns of the row-major\n"
"vectors (9)) of the symmetric 3x3 matrix (9, row-major), as np.linalg.eigh returns them.\n"
"False if an entry is not finite.");

static PyObject *
py_symmetric_eigen(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const BufferSpec specs[3] = {{0, "matrix", 9, 0}, {1, "values", 3, 1},
                                        {2, "vectors", 9, 1}};
    Py_buffer v[3];
    if (check_nargs(nargs, 3, "symmetric_eigen") || acquire(args, specs, 3, v)) return NULL;
    int status = symmetric_eigen(v[0].buf, v[1].buf, v[2].buf);
    release(v, 3);
    return PyBool_FromLong(status == 0);
}

PyDoc_STRVAR(smooth_min_doc,
"smooth_min(eigenvalues, exponent, floor, log_gap, out)\n--\n\n"
"lambda-bar, the clipped eigenvalues (3), g (3), the eigen-Hessian h00 h11 h22 h01 h02 h12\n"
"and the divided differences t01 t02 t12 into out (16), from ascending eigenvalues (3):\n"
"smooth_min.smooth_min_eigenvalue's coefficients.");

static PyObject *
py_smooth_min(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const BufferSpec specs[2] = {{0, "eigenvalues", 3, 0}, {4, "out", N_SMOOTH, 1}};
    Py_buffer v[2];
    if (check_nargs(nargs, 5, "smooth_min")) return NULL;
    double p = PyFloat_AsDouble(args[1]);
    SmoothMinLimits lim = {PyFloat_AsDouble(args[2]), PyFloat_AsDouble(args[3])};
    if (PyErr_Occurred() || acquire(args, specs, 2, v)) return NULL;
    smooth_min(v[0].buf, p, lim, v[1].buf);
    release(v, 2);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(perception_barrier_doc,
"perception_barrier(drone, estimates, velocities, gramians, projector_means, constants, out)"
" -> bool\n--\n\n"
"Per target r of M: the perception terms of the drone (3) and estimates[r, :3]\n"
"(estimates: M x n), then the barrier of its Gramian copy gramians[r] (M x 9) and consensus\n"
"mean s = projector_means[r] (M x 9) with the target velocity velocities[r] (M x 3), into\n"
"out[r] (M x 24, ROW_FIELDS): perception (17: w, dw/dp_i, unit bearing, distance,\n"
"projector), then lambda-bar, psi0, psi1, L_g psi1 (3), lower bound. constants (13,\n"
"BARRIER_CONSTANTS): the perception constants (6),\n"
"N, rho, epsilon, p, b, EIGENVALUE_FLOOR, NEAR_REPEATED_LOG_GAP. False if a Gramian copy\n"
"has a non-finite entry (out is then incomplete).");

/* perception_barrier's constants: the perception constants, then these; exported as
 * BARRIER_CONSTANTS. */
enum { C_N = N_PERCEPTION_CONSTANTS, C_RHO, C_EPS, C_P, C_B, C_FLOOR, C_GAP, N_CONSTANTS };
static const char *const barrier_constant_names[N_CONSTANTS] = {  /* after the perception's */
    [C_N] = "n_agents", [C_RHO] = "forgetting", [C_EPS] = "epsilon", [C_P] = "exponent",
    [C_B] = "info_gain", [C_FLOOR] = "eigenvalue_floor", [C_GAP] = "near_repeated_log_gap"};
#define N_ROW (N_PERCEPTION + N_BARRIER)

static PyObject *
py_perception_barrier(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const BufferSpec specs[7] = {
        {0, "drone", 3, 0}, {1, "estimates", -1, 0}, {2, "velocities", -1, 0},
        {3, "gramians", -1, 0}, {4, "projector_means", -1, 0}, {5, "constants", N_CONSTANTS, 0},
        {6, "out", -1, 1}};
    Py_buffer v[7];
    if (check_nargs(nargs, 7, "perception_barrier") || acquire(args, specs, 7, v)) return NULL;
    Py_ssize_t m = v[3].len / 8 / 9, n = m > 0 ? v[1].len / 8 / m : 0;
    if (m < 1 || n < 3 || n > MAX_STATE) {
        PyErr_Format(PyExc_ValueError, "perception_barrier: gramians (%zd values) and "
                     "estimates (%zd) are not M x 9 and M x n (3 <= n <= 6)",
                     v[3].len / 8, v[1].len / 8);
        release(v, 7);
        return NULL;
    }
    const Py_ssize_t lengths[7] = {3, n * m, 3 * m, 9 * m, 9 * m, N_CONSTANTS, N_ROW * m};
    if (check_lengths(v, specs, lengths, 7)) return NULL;
    const double *drone = v[0].buf, *estimates = v[1].buf, *velocities = v[2].buf;
    const double *gramians = v[3].buf, *means = v[4].buf, *k = v[5].buf;
    double *out = v[6].buf;
    BarrierConstants b = {k[C_N], k[C_RHO], k[C_EPS], k[C_P], k[C_B]};
    SmoothMinLimits lim = {k[C_FLOOR], k[C_GAP]};
    int ok = 1;
    for (Py_ssize_t r = 0; r < m && ok; r++) {
        double *row = out + N_ROW * r, values[3], vectors[9];
        perception(drone, estimates + n * r, k, row);
        if (symmetric_eigen(gramians + 9 * r, values, vectors) != 0) { ok = 0; break; }
        localization_barrier(values, vectors, means + 9 * r, row, velocities + 3 * r, b, lim,
                             row + N_PERCEPTION);
    }
    release(v, 7);
    return PyBool_FromLong(ok);
}

PyDoc_STRVAR(filter_stack_doc,
"filter_stack(information, vector, transition, process_noise, n_agents, posterior_state,"
" prior_state, prior_information, posterior_covariance) -> bool\n--\n\n"
"icf.posterior, posterior_covariance and predict (without the communicated velocity) for\n"
"M targets: information (M x n x n), vector (M x n), transition A (n x n), into the four\n"
"outputs (M x n, M x n, M x n x n, M x n x n). False if some V or A P A' + qI is not\n"
"positive definite (the outputs are then incomplete: take the pseudo-inverse path).");

static PyObject *
py_filter_stack(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const BufferSpec specs[7] = {
        {0, "information", -1, 0}, {1, "vector", -1, 0}, {2, "transition", -1, 0},
        {5, "posterior_state", -1, 1}, {6, "prior_state", -1, 1},
        {7, "prior_information", -1, 1}, {8, "posterior_covariance", -1, 1}};
    Py_buffer v[7];
    if (check_nargs(nargs, 9, "filter_stack")) return NULL;
    double process_noise = PyFloat_AsDouble(args[3]);
    double n_agents = PyFloat_AsDouble(args[4]);
    if (PyErr_Occurred() || acquire(args, specs, 7, v)) return NULL;
    Py_ssize_t nn = v[2].len / 8, n = (Py_ssize_t)lround(sqrt((double)nn));
    Py_ssize_t m = n > 0 ? v[1].len / 8 / n : 0;
    if (n < 1 || n > MAX_STATE || n * n != nn || m < 1) {
        PyErr_Format(PyExc_ValueError, "filter_stack: transition must be n x n with n <= %d "
                     "and vector M x n, got %zd and %zd values", MAX_STATE, nn, v[1].len / 8);
        release(v, 7);
        return NULL;
    }
    const Py_ssize_t lengths[7] = {m * n * n, m * n, n * n, m * n, m * n, m * n * n, m * n * n};
    if (check_lengths(v, specs, lengths, 7)) return NULL;
    int status = filter_stack(v[0].buf, v[1].buf, v[2].buf, (int)m, (int)n, process_noise,
                              n_agents, v[3].buf, v[4].buf, v[5].buf, v[6].buf);
    release(v, 7);
    return PyBool_FromLong(status == 0);
}

static Py_ssize_t
sequence_length(PyObject *seq)
{
    return PyList_Check(seq) || PyTuple_Check(seq) ? PySequence_Fast_GET_SIZE(seq) : -1;
}

/* One list or tuple argument of a kernel: which of the call's arguments and its name. */
typedef struct {
    int arg;
    const char *name;
} SequenceSpec;

/* The floats of `count` sequences (args[specs[i].arg], lengths[i] floats each), one after the
 * other in one new block that the caller frees with PyMem_Free; NULL with a one-line error
 * naming the first that is not a list or tuple of that many numbers. */
static double *
read_floats(PyObject *const *args, const SequenceSpec *specs, const Py_ssize_t *lengths,
            int count)
{
    Py_ssize_t total = 1;
    for (int i = 0; i < count; i++) total += lengths[i];
    double *block = PyMem_Malloc(sizeof(double) * (size_t)total);
    if (block == NULL) {
        PyErr_NoMemory();
        return NULL;
    }
    double *at = block;
    for (int i = 0; i < count; i++) {
        if (float_sequence(args[specs[i].arg], at, lengths[i], specs[i].name) != 0) {
            PyMem_Free(block);
            return NULL;
        }
        at += lengths[i];
    }
    return block;
}

PyDoc_STRVAR(qp_load_doc,
"qp_load(columns, lower, nominal, low, high, weights, slack_weight, weight_floor, rows,\n"
" bounds_lower, bounds_upper, linear, hessian) -> bool\n--\n\n"
"Writes the local QP of one solve into LocalQpWorkspace's arrays: the u columns (3R floats,\n"
"column-major) into rows (R x n_z), lower (R) after the n_z bounds of z in bounds_lower\n"
"(n_z + R), the box of u (low, high: 3 each) into both bound arrays, -2 u_d into linear\n"
"(n_z) and the slack penalties 2 K max(w, floor) of the M weights into the diagonal of the\n"
"hessian (n_z x n_z) when n_z = 3 + 2M. Lists or tuples for the inputs, float64 arrays for\n"
"the outputs. Returns whether the hessian changed.");

static PyObject *
py_qp_load(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 13, "qp_load")) return NULL;
    double slack_weight = PyFloat_AsDouble(args[6]), weight_floor = PyFloat_AsDouble(args[7]);
    if (PyErr_Occurred()) return NULL;
    Py_ssize_t n_rows = sequence_length(args[1]), n_weights = sequence_length(args[5]);
    if (n_rows < 0 || n_weights < 0) {
        PyErr_SetString(PyExc_TypeError, "qp_load: lower and weights must be lists or tuples "
                        "of floats");
        return NULL;
    }
    static const BufferSpec specs[5] = {{8, "rows", -1, 1}, {9, "bounds_lower", -1, 1},
                                        {10, "bounds_upper", -1, 1}, {11, "linear", -1, 1},
                                        {12, "hessian", -1, 1}};
    Py_buffer v[5];
    if (acquire(args, specs, 5, v)) return NULL;
    Py_ssize_t n_z = v[3].len / 8;
    const Py_ssize_t lengths[5] = {n_rows * n_z, n_z + n_rows, n_z + n_rows, n_z, n_z * n_z};
    if (check_lengths(v, specs, lengths, 5)) return NULL;
    Py_ssize_t m = (n_z - 3) / 2;
    if (n_z < 3 || (n_z > 3 && (n_z - 3) % 2) || (n_z > 3 && n_weights != m)) {
        PyErr_Format(PyExc_ValueError, "qp_load: %zd variables and %zd weights, expected 3 (hard)"
                     " or 3 + 2M with M weights (relaxed)", n_z, n_weights);
        release(v, 5);
        return NULL;
    }
    static const SequenceSpec inputs[6] = {{0, "columns"}, {1, "lower"}, {2, "nominal"},
                                           {3, "low"}, {4, "high"}, {5, "weights"}};
    const Py_ssize_t sizes[6] = {3 * n_rows, n_rows, 3, 3, 3, n_weights};
    double *columns = read_floats(args, inputs, sizes, 6);
    if (columns == NULL) {
        release(v, 5);
        return NULL;
    }
    double *lower = columns + 3 * n_rows, *nominal = lower + n_rows, *low = nominal + 3;
    double *high = low + 3, *weights = high + 3;
    PyObject *result = PyBool_FromLong(qp_load(
        columns, lower, n_rows, nominal, low, high, weights, slack_weight, weight_floor, n_z,
        v[0].buf, v[1].buf, v[2].buf, v[3].buf, v[4].buf));
    PyMem_Free(columns);
    release(v, 5);
    return result;
}

PyDoc_STRVAR(qp_max_violation_doc,
"qp_max_violation(z, columns, lower, low, high) -> float\n--\n\n"
"The largest violation of the local QP at z = [u (3), slacks] (0.0 if feasible), from lists\n"
"or tuples of floats: the rows' velocity columns (3R, column-major: every row's x, then y,\n"
"then z), their lower bounds (R; slack r enters row r), the box of u (3 and 3):\n"
"qp.LocalQp.max_violation of that QP. A NaN row gap is returned as the violation.");

static PyObject *
py_qp_max_violation(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 5, "qp_max_violation")) return NULL;
    Py_ssize_t n_z = sequence_length(args[0]), n_rows = sequence_length(args[2]);
    if (n_z < 3 || n_rows < 0) {
        PyErr_SetString(PyExc_ValueError, "qp_max_violation: z must be a list or tuple of at "
                        "least 3 floats and lower a list or tuple of floats");
        return NULL;
    }
    static const SequenceSpec inputs[5] = {{0, "z"}, {1, "columns"}, {2, "lower"},
                                           {3, "low"}, {4, "high"}};
    const Py_ssize_t sizes[5] = {n_z, 3 * n_rows, n_rows, 3, 3};
    double *z = read_floats(args, inputs, sizes, 5);
    if (z == NULL) return NULL;
    double *columns = z + n_z, *lower = columns + 3 * n_rows, *low = lower + n_rows;
    PyObject *result = PyFloat_FromDouble(qp_max_violation(z, n_z, columns, lower, n_rows, low,
                                                           low + 3));
    PyMem_Free(z);
    return result;
}

/* Row constants of qp_rows, in this order; exported as QP_ROW_CONSTANTS. */
enum { R_N, R_GAMMA, R_RADIUS, R_DELTA, R_GAIN, R_BOUND, R_SHARE, N_ROW_CONSTANTS };
static const char *const row_constant_names[N_ROW_CONSTANTS] = {
    [R_N] = "n_agents", [R_GAMMA] = "gamma", [R_RADIUS] = "collision_radius_m",
    [R_DELTA] = "collision_distance_m", [R_GAIN] = "collision_gain",
    [R_BOUND] = "tracking_error_bound_m_s", [R_SHARE] = "localization_share"};
/* The values of R_SHARE, exported as LOCALIZATION_SHARES (control.localization_share):
 * SHARE_EQUAL, each drone's share of the localization condition is 1/N (SPEC 8, 3.32);
 * SHARE_WEIGHTED, w_ir / max(S_wr, w_ir) (3.27-3.28, barrier.localization_share). */
enum { SHARE_EQUAL, SHARE_WEIGHTED, N_SHARES };
static const char *const share_names[N_SHARES] = {
    [SHARE_EQUAL] = "equal", [SHARE_WEIGHTED] = "weighted"};

/* The float triples of a list or tuple of `count` triples, into out (3 count); -1 with a
 * one-line error naming `what` and the entry otherwise. */
static int
triples(PyObject *seq, Py_ssize_t count, double *out, const char *what)
{
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (Py_ssize_t i = 0; i < count; i++)
        if (float_sequence(items[i], out + 3 * i, 3, what) != 0) {
            char name[64];  /* the same error again, naming the entry */
            snprintf(name, sizeof name, "%s[%zd]", what, i);
            PyErr_Clear();
            float_sequence(items[i], out + 3 * i, 3, name);
            return -1;
        }
    return 0;
}

PyDoc_STRVAR(qp_rows_doc,
"qp_rows(terms, velocities, weight_sums, position, others, envelope_rows, envelope_lower,\n"
" constants) -> (columns, lower)\n--\n\n"
"The rows a.u >= b of the local QP (SPEC 8), as LocalQpWorkspace.solve takes them: the\n"
"velocity parts column-major (every row's x, then y, then z) and the lower bounds, both new\n"
"lists. Rows in order: localization (3.32: L_g psi1 and the bound of perception_barrier's\n"
"rows, `terms`, M x 24 float64), weight-sum (3.34-3.36: dw/dp_i and -(S_w - gamma)/N +\n"
"dw/dp_i.v, with `velocities` M x 3 float64 and the M `weight_sums` S_w), one collision row\n"
"(4.1-4.2: 2(p_i - p_j) and -alpha h/2) per entry of `others` (float triples, in their order)\n"
"within the collision radius of `position`, then the `envelope_rows` (triples) with their\n"
"`envelope_lower`. Every bound is then tightened to b + e||a|| when e > 0 (robust_lower_bound).\n"
"`constants` (QP_ROW_CONSTANTS): N, gamma, collision radius, collision distance, collision\n"
"gain, e, share (LOCALIZATION_SHARES): equal (0) keeps the localization bounds (each\n"
"drone's share 1/N of 3.27), weighted (1) gives drone i the share k = w_ir / max(S_w, w_ir)\n"
"(0 if w_ir = 0): bound -k(c + psi1) - d_i.");

static PyObject *
py_qp_rows(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 8, "qp_rows")) return NULL;
    Py_ssize_t m = sequence_length(args[2]), n_others = sequence_length(args[4]),
               n_envelope = sequence_length(args[5]);
    if (m < 0 || n_others < 0 || n_envelope < 0) {
        PyErr_SetString(PyExc_TypeError, "qp_rows: weight_sums, others and envelope_rows must "
                        "be lists or tuples");
        return NULL;
    }
    static const BufferSpec specs[2] = {{0, "terms", -1, 0}, {1, "velocities", -1, 0}};
    Py_buffer v[2];
    if (acquire(args, specs, 2, v)) return NULL;
    const Py_ssize_t lengths[2] = {m * (N_PERCEPTION + N_BARRIER), 3 * m};
    if (check_lengths(v, specs, lengths, 2)) return NULL;
    static const SequenceSpec inputs[4] = {{2, "weight_sums"}, {3, "position"},
                                           {6, "envelope_lower"}, {7, "constants"}};
    const Py_ssize_t sizes[4] = {m, 3, n_envelope, N_ROW_CONSTANTS};
    double *block = read_floats(args, inputs, sizes, 4);
    /* work: the triples of others and envelope rows, then the rows (3 R) and bounds (R) */
    Py_ssize_t most = 2 * m + n_others + n_envelope;
    double *work = block == NULL ? NULL
                   : PyMem_Malloc(sizeof(double) * (size_t)(3 * (n_others + n_envelope)
                                                            + 4 * most + 1));
    PyObject *result = NULL;
    if (work == NULL) {
        if (block != NULL) PyErr_NoMemory();
        goto done;
    }
    const double *weight_sums = block, *position = block + m, *envelope_lower = position + 3,
                 *c = envelope_lower + n_envelope;
    double *others = work, *envelope = others + 3 * n_others, *a = envelope + 3 * n_envelope,
           *lower = a + 3 * most;
    if (triples(args[4], n_others, others, "others")
            || triples(args[5], n_envelope, envelope, "envelope_rows"))
        goto done;
    const double *terms = v[0].buf, *velocity = v[1].buf;
    Py_ssize_t r = 0;
    if (c[R_SHARE] != SHARE_EQUAL && c[R_SHARE] != SHARE_WEIGHTED) {
        PyErr_Format(PyExc_ValueError, "qp_rows: constants[%d] (the localization share) must "
                     "be %d (1/N) or %d (weighted), got %R", (int)R_SHARE, (int)SHARE_EQUAL,
                     (int)SHARE_WEIGHTED,
                     PySequence_Fast_ITEMS(args[7])[R_SHARE]);
        goto done;
    }
    for (Py_ssize_t t = 0; t < m; t++, r++) {  /* localization (3.32) */
        const double *row = terms + t * (N_PERCEPTION + N_BARRIER),
                     *barrier = row + N_PERCEPTION;
        for (int k = 0; k < 3; k++) a[3 * r + k] = barrier[B_LIE + k];
        lower[r] = barrier[B_LOWER];
        if (c[R_SHARE] == SHARE_WEIGHTED) {  /* (3.27), k = w / max(S_w, w): -k(c + psi1) - d_i */
            const double *vel = velocity + 3 * t;
            double w = row[P_WEIGHT], sum = weight_sums[t];
            double share = w > 0.0 ? w / (sum > w ? sum : w) : 0.0;
            /* d_i as localization_barrier computes it; B_LOWER + d_i = -(c + psi1)/N */
            double drift = -(barrier[B_LIE] * vel[0] + barrier[B_LIE + 1] * vel[1]
                             + barrier[B_LIE + 2] * vel[2]);
            lower[r] = c[R_N] * share * (barrier[B_LOWER] + drift) - drift;
        }
    }
    for (Py_ssize_t t = 0; t < m; t++, r++) {  /* weight sum (3.34-3.36) */
        const double *grad = terms + t * (N_PERCEPTION + N_BARRIER) + P_GRAD,
                     *vel = velocity + 3 * t;
        for (int k = 0; k < 3; k++) a[3 * r + k] = grad[k];
        lower[r] = -(weight_sums[t] - c[R_GAMMA]) / c[R_N]
                   + (grad[0] * vel[0] + grad[1] * vel[1] + grad[2] * vel[2]);
    }
    for (Py_ssize_t j = 0; j < n_others; j++) {  /* collision (4.1-4.2), within R_ca */
        double ox = position[0] - others[3 * j], oy = position[1] - others[3 * j + 1],
               oz = position[2] - others[3 * j + 2];
        double square = ox * ox + oy * oy + oz * oz;
        if (!(sqrt(square) <= c[R_RADIUS])) continue;
        a[3 * r] = 2.0 * ox, a[3 * r + 1] = 2.0 * oy, a[3 * r + 2] = 2.0 * oz;
        lower[r++] = -0.5 * c[R_GAIN] * (square - c[R_DELTA] * c[R_DELTA]);
    }
    for (Py_ssize_t e = 0; e < n_envelope; e++, r++) {  /* the safety envelope's rows */
        for (int k = 0; k < 3; k++) a[3 * r + k] = envelope[3 * e + k];
        lower[r] = envelope_lower[e];
    }
    if (c[R_BOUND] > 0.0)  /* robust_lower_bound: b + e||a|| */
        for (Py_ssize_t i = 0; i < r; i++) {
            const double *row = a + 3 * i;
            lower[i] = lower[i] + c[R_BOUND] * sqrt(row[0] * row[0] + row[1] * row[1]
                                                    + row[2] * row[2]);
        }
    double *columns = PyMem_Malloc(sizeof(double) * (size_t)(3 * r + 1));
    if (columns == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t i = 0; i < r; i++)
        for (int k = 0; k < 3; k++) columns[k * r + i] = a[3 * i + k];
    PyObject *column_list = float_list(columns, 3 * r);
    PyMem_Free(columns);
    PyObject *lower_list = column_list == NULL ? NULL : float_list(lower, r);
    if (lower_list != NULL) result = PyTuple_Pack(2, column_list, lower_list);
    Py_XDECREF(column_list);
    Py_XDECREF(lower_list);
done:
    PyMem_Free(work);
    PyMem_Free(block);
    release(v, 2);
    return result;
}

PyDoc_STRVAR(initial_information_doc,
"initial_information(prior_information, prior_state, n_agents, info_gain, seen_from,\n"
" image_points, detected, out)\n--\n\n"
"icf.initial_information of M targets into out, the ICF pair in the order of ICF_PAIR:\n"
"V0 (M x n x n) and v0 (M x n). From the prior\n"
"information (M x n x n) and state (M x n) arrays, N, b, where the image was taken (3 floats),\n"
"the measured image points (2M floats) and detected flags (M floats, 0: not seen), lists.");

static PyObject *
py_initial_information(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 8, "initial_information")) return NULL;
    static const BufferSpec specs[3] = {{0, "prior_information", -1, 0},
                                        {1, "prior_state", -1, 0}, {7, "out", -1, 1}};
    Py_buffer v[3];
    double n_agents = PyFloat_AsDouble(args[2]), gain = PyFloat_AsDouble(args[3]);
    if (PyErr_Occurred()) return NULL;
    Py_ssize_t m = PyList_Check(args[6]) ? PyList_GET_SIZE(args[6]) : -1;
    if (m < 1) {
        PyErr_SetString(PyExc_TypeError, "initial_information: detected must be a non-empty "
                        "list of floats");
        return NULL;
    }
    if (acquire(args, specs, 3, v)) return NULL;
    Py_ssize_t n = v[1].len / 8 / m;
    if (n < 1 || n > MAX_STATE || n * m != v[1].len / 8) {
        PyErr_Format(PyExc_ValueError, "initial_information: prior_state holds %zd values, "
                     "not M = %zd rows of n <= %d", v[1].len / 8, m, MAX_STATE);
        release(v, 3);
        return NULL;
    }
    const Py_ssize_t lengths[3] = {m * n * n, m * n, m * n * n + m * n};
    if (check_lengths(v, specs, lengths, 3)) return NULL;
    static const SequenceSpec inputs[3] = {{4, "seen_from"}, {5, "image_points"},
                                           {6, "detected"}};
    const Py_ssize_t sizes[3] = {3, 2 * m, m};
    double *seen_from = read_floats(args, inputs, sizes, 3);
    if (seen_from == NULL) {
        release(v, 3);
        return NULL;
    }
    const Py_ssize_t parts_sizes[N_PAIR_PARTS] = {[I_INFORMATION] = m * n * n,
                                                 [I_VECTOR] = m * n};
    double *parts[N_PAIR_PARTS], *at = v[2].buf;
    for (int p = 0; p < N_PAIR_PARTS; p++) {
        parts[p] = at;
        at += parts_sizes[p];
    }
    initial_information(v[0].buf, v[1].buf, (int)m, (int)n, n_agents, gain, seen_from,
                        seen_from + 3, seen_from + 3 + 2 * m, parts[I_INFORMATION],
                        parts[I_VECTOR]);
    PyMem_Free(seen_from);
    release(v, 3);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(consensus_sums_doc,
"consensus_sums(own_icf, own_cons, blocks, weights, icf_out, disagreement_out) -> int\n--\n\n"
"One ICF consensus iteration of the packed pair own_icf (n floats) with the neighbours'\n"
"blocks (a list of float64 arrays, each starting with its pair) weighted by weights (a list\n"
"of floats): icf_out = a + sum_j w_j (a_j - a). With own_cons (the round-0 consensus\n"
"states, m floats; None in later rounds) the blocks carry [pair | states] and\n"
"disagreement_out = -sum_j (c_j - c) (zeros without a block). A block with a non-finite\n"
"value among the floats used is left out; returns how many were.");

static PyObject *
py_consensus_sums(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 6, "consensus_sums")) return NULL;
    int first = args[1] != Py_None;
    PyObject *blocks = args[2], *weight_list = args[3];
    if (!PyList_Check(blocks) || !PyList_Check(weight_list)
            || PyList_GET_SIZE(blocks) != PyList_GET_SIZE(weight_list)) {
        PyErr_SetString(PyExc_TypeError, "consensus_sums: blocks and weights must be lists of "
                        "the same length");
        return NULL;
    }
    if (first == (args[5] == Py_None)) {
        PyErr_SetString(PyExc_TypeError, "consensus_sums: own_cons and disagreement_out go "
                        "together (both None after round 0)");
        return NULL;
    }
    Py_ssize_t count = PyList_GET_SIZE(blocks);
    static const BufferSpec specs[4] = {{0, "own_icf", -1, 0}, {4, "icf_out", -1, 1},
                                        {1, "own_cons", -1, 0}, {5, "disagreement_out", -1, 1}};
    Py_buffer v[4];
    int n_views = first ? 4 : 2;
    if (acquire(args, specs, n_views, v)) return NULL;
    Py_ssize_t n_icf = v[0].len / 8, n_cons = first ? v[2].len / 8 : 0;
    const Py_ssize_t lengths[4] = {n_icf, n_icf, n_cons, n_cons};
    if (check_lengths(v, specs, lengths, n_views)) return NULL;
    /* Scratch: the views of the blocks, their data and weights. */
    Py_buffer *views = PyMem_Calloc((size_t)count + 1, sizeof(Py_buffer));
    const double **data = PyMem_Calloc((size_t)count + 1, sizeof(double *));
    double *weights = PyMem_Calloc((size_t)count + 1, sizeof(double));
    Py_ssize_t held = 0, used = 0, dropped = 0;
    PyObject *result = NULL;
    if (views == NULL || data == NULL || weights == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t j = 0; j < count; j++) {
        if (float64_buffer(PyList_GET_ITEM(blocks, j), &views[held], 0, -1, "block")) goto done;
        held++;
        if (views[held - 1].len / 8 < n_icf + n_cons) {
            PyErr_Format(PyExc_ValueError, "consensus_sums: block %zd holds %zd floats, "
                         "expected at least %zd", j, views[held - 1].len / 8, n_icf + n_cons);
            goto done;
        }
        double weight = PyFloat_AsDouble(PyList_GET_ITEM(weight_list, j));
        if (weight == -1.0 && PyErr_Occurred()) goto done;
        const double *block = views[held - 1].buf;
        if (!all_finite(block, n_icf + n_cons)) {
            dropped++;
            continue;
        }
        data[used] = block;
        weights[used++] = weight;
    }
    consensus_sums(v[0].buf, n_icf, first ? v[2].buf : NULL, n_cons, data, weights, used,
                   v[1].buf, first ? v[3].buf : NULL);
    if (first && used == 0) memset(v[3].buf, 0, (size_t)n_cons * sizeof(double));
    result = PyLong_FromSsize_t(dropped);
done:
    release(views, (int)held);
    release(v, n_views);
    PyMem_Free(views);
    PyMem_Free(data);
    PyMem_Free(weights);
    return result;
}

PyDoc_STRVAR(consensus_step_doc,
"consensus_step(x, d, u, index, coefficients, out)\n--\n\n"
"out[i] = sum_r coefficients[r, i] * z[index[r, i]] (products, then added from r = 0) with\n"
"z = x (n), d (n), u (a list of floats) and 0, in the order of CONSENSUS_STEP_Z:\n"
"np.add.reduce(z[index] * coefficients, axis=0) of drone_step._consensus_operator's (index,\n"
"coefficients), both (rows, n).");

static PyObject *
py_consensus_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (check_nargs(nargs, 6, "consensus_step")) return NULL;
    static const BufferSpec specs[4] = {{0, "x", -1, 0}, {1, "d", -1, 0},
                                        {4, "coefficients", -1, 0}, {5, "out", -1, 1}};
    Py_buffer v[4], index;
    Py_ssize_t n_u = PyList_Check(args[2]) ? PyList_GET_SIZE(args[2]) : -1;
    if (n_u < 0) {
        PyErr_SetString(PyExc_TypeError, "consensus_step: u must be a list of floats");
        return NULL;
    }
    if (acquire(args, specs, 4, v)) return NULL;
    Py_ssize_t n = v[0].len / 8, terms = v[2].len / 8;
    const Py_ssize_t lengths[4] = {n, n, terms, n};
    if (check_lengths(v, specs, lengths, 4)) return NULL;
    if (PyObject_GetBuffer(args[3], &index, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) != 0) {
        release(v, 4);
        return NULL;
    }
    const char *format = index.format ? index.format : "B";
    int integers = index.itemsize == (Py_ssize_t)sizeof(Py_ssize_t)
                   && strchr("lLqQn", format[strlen(format) - 1]) != NULL;
    /* z: its parts one after the other, in the order of the Z_ enum */
    const Py_ssize_t sizes[N_Z_PARTS] = {[Z_STATE] = n, [Z_DISAGREEMENT] = n, [Z_INPUT] = n_u,
                                         [Z_ZERO] = 1};
    Py_ssize_t starts[N_Z_PARTS], n_z = 0;
    for (int p = 0; p < N_Z_PARTS; p++) {
        starts[p] = n_z;
        n_z += sizes[p];
    }
    double *z = NULL;
    PyObject *result = NULL;
    if (!integers || n == 0 || terms % n != 0 || index.len / index.itemsize != terms) {
        PyErr_Format(PyExc_ValueError, "consensus_step: index (%zd items of format '%s') and "
                     "coefficients (%zd) must both be (rows, n = %zd), index of intp", index.len
                     / (index.itemsize ? index.itemsize : 1), format, terms, n);
    } else if ((z = PyMem_Malloc(sizeof(double) * (size_t)n_z)) == NULL) {
        PyErr_NoMemory();
    } else if (float_sequence(args[2], z + starts[Z_INPUT], n_u, "u") == 0) {
        memcpy(z + starts[Z_STATE], v[0].buf, sizeof(double) * (size_t)n);
        memcpy(z + starts[Z_DISAGREEMENT], v[1].buf, sizeof(double) * (size_t)n);
        z[starts[Z_ZERO]] = 0.0;
        const Py_ssize_t *at = index.buf;
        int in_range = 1;
        for (Py_ssize_t k = 0; k < terms; k++)
            if (at[k] < 0 || at[k] >= n_z) in_range = 0;
        if (!in_range) {
            PyErr_Format(PyExc_ValueError, "consensus_step: an index lies outside z (%zd "
                         "floats)", n_z);
        } else {
            consensus_step(z, n, at, v[2].buf, terms / n, v[3].buf);
            result = Py_None;
            Py_INCREF(result);
        }
    }
    PyMem_Free(z);
    PyBuffer_Release(&index);
    release(v, 4);
    return result;
}

static PyMethodDef methods[] = {
    {"perception", (PyCFunction)(void (*)(void))py_perception, METH_FASTCALL, perception_doc},
    {"symmetric_eigen", (PyCFunction)(void (*)(void))py_symmetric_eigen, METH_FASTCALL,
     symmetric_eigen_doc},
    {"smooth_min", (PyCFunction)(void (*)(void))py_smooth_min, METH_FASTCALL, smooth_min_doc},
    {"perception_barrier", (PyCFunction)(void (*)(void))py_perception_barrier, METH_FASTCALL,
     perception_barrier_doc},
    {"filter_stack", (PyCFunction)(void (*)(void))py_filter_stack, METH_FASTCALL,
     filter_stack_doc},
    {"qp_load", (PyCFunction)(void (*)(void))py_qp_load, METH_FASTCALL, qp_load_doc},
    {"qp_max_violation", (PyCFunction)(void (*)(void))py_qp_max_violation, METH_FASTCALL,
     qp_max_violation_doc},
    {"qp_rows", (PyCFunction)(void (*)(void))py_qp_rows, METH_FASTCALL, qp_rows_doc},
    {"initial_information", (PyCFunction)(void (*)(void))py_initial_information,
     METH_FASTCALL, initial_information_doc},
    {"consensus_sums", (PyCFunction)(void (*)(void))py_consensus_sums, METH_FASTCALL,
     consensus_sums_doc},
    {"consensus_step", (PyCFunction)(void (*)(void))py_consensus_step, METH_FASTCALL,
     consensus_step_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "swarm.core._kernels",
    .m_doc = "The per-step numerical kernels of DroneAgent, compiled (see the source's header).",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC
PyInit__kernels(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL) return NULL;
    /* perception_barrier's constants: the perception constants, then its own */
    const char *barrier_names[N_CONSTANTS];
    for (int i = 0; i < N_CONSTANTS; i++)
        barrier_names[i] = i < N_PERCEPTION_CONSTANTS ? perception_constant_names[i]
                                                      : barrier_constant_names[i];
    if (PyModule_AddIntConstant(mod, "PERCEPTION_SIZE", N_PERCEPTION) < 0
            || PyModule_AddIntConstant(mod, "BARRIER_SIZE", N_BARRIER) < 0
            || PyModule_AddIntConstant(mod, "SMOOTH_MIN_SIZE", N_SMOOTH) < 0
            || PyModule_AddIntConstant(mod, "CONSTANTS_SIZE", N_CONSTANTS) < 0
            || PyModule_AddIntConstant(mod, "MAX_STATE", MAX_STATE) < 0
            || add_fields(mod, "ROW_FIELDS", row_fields, COUNT(row_fields),
                          N_PERCEPTION + N_BARRIER) < 0
            || add_fields(mod, "SMOOTH_MIN_FIELDS", smooth_min_fields, COUNT(smooth_min_fields),
                          N_SMOOTH) < 0
            || add_names(mod, "PERCEPTION_CONSTANTS", perception_constant_names,
                         N_PERCEPTION_CONSTANTS) < 0
            || add_names(mod, "BARRIER_CONSTANTS", barrier_names, N_CONSTANTS) < 0
            || add_names(mod, "QP_ROW_CONSTANTS", row_constant_names, N_ROW_CONSTANTS) < 0
            || add_names(mod, "LOCALIZATION_SHARES", share_names, N_SHARES) < 0
            || add_names(mod, "ICF_PAIR", pair_part_names, N_PAIR_PARTS) < 0
            || add_names(mod, "CONSENSUS_STEP_Z", z_part_names, N_Z_PARTS) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
