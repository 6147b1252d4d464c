/* The IPF reward's kernel (the torch reference: sim/ipf.py IPFGrid.agent_potentials).
 * Compiled as part of kernels.c. */
#include "common.h"

/* Pass 3 of agv_ipf for environment b (see there): the task factor where stale, then the
 * Schur complement's factor and the values. Called with compile-time sizes for the common
 * full scenes, so that the small loops unroll; returns 1 when a block was not positive
 * definite. */
static inline __attribute__((always_inline)) int ipf_values(
        const int64_t N, const int64_t M, const int64_t mt, const int64_t na, int64_t b,
        int64_t T, const int64_t *cell, const int64_t *src, const int64_t *aslot,
        const uint8_t *cand, const int64_t *cnt, int64_t *tcache, double *dcache,
        const double *stage, int64_t GT, int64_t GA, double *l, double *inv, double *x,
        double *sc, double *r, double *z, double *y, double agent_value, double task_value,
        const int64_t *agent_task, const uint8_t *active, double *out, float *out32) {
    int status = 0;
    const int64_t *ce = cell + b * T, *sr = src + b * T, *as = aslot + b * N;
    const uint8_t *ca = cand + b * T;
    int64_t *tc = tcache + b * (M + 1);
    double *linv = dcache + b * (M * M + M), *u = linv + M * M;
    if (cnt[4 * b + 2]) {  /* the tasks' factor L (row by row), L^-1, u = L^-1 v_T */
        const double *st = stage + b * (GT + GA);
        for (int64_t p = 0; p < mt; p++) {
            double *lp = l + p * M;
            for (int64_t q = 0; q <= p; q++) {
                double sum = *st++;
                for (int64_t k = 0; k < q; k++) sum -= lp[k] * l[q * M + k];
                if (q < p) {
                    lp[q] = sum * inv[q];
                } else {
                    if (!(sum > 0.0)) status = 1;
                    lp[p] = sqrt(sum);
                    inv[p] = 1.0 / lp[p];
                }
            }
        }
        for (int64_t q = 0; q < mt; q++) {
            for (int64_t p = 0; p < mt; p++) {
                double sum = p == q ? 1.0 : 0.0;
                if (p > q)
                    for (int64_t k = q; k < p; k++) sum -= l[p * M + k] * linv[k * M + q];
                linv[p * M + q] = p < q ? 0.0 : sum * inv[p];
            }
        }
        for (int64_t p = 0; p < mt; p++) {
            double sum = 0.0;
            for (int64_t q = 0; q <= p; q++) sum += linv[p * M + q];
            u[p] = sum * task_value;
        }
        tc[0] = mt;
        for (int64_t p = 0; p < mt; p++) tc[1 + p] = sr[p];
    }
    /* X = G[A, T] L^-T, r = v_A - X u, S = G[A, A] - X X^T. */
    const double *st = stage + b * (GT + GA) + GT;
    for (int64_t a = 0; a < na; a++) {
        const double *gt = st, *gaa = st + mt;
        st += mt + a + 1;
        double *xa = x + a * M;
        double ra = agent_value;
        for (int64_t p = 0; p < mt; p++) {
            const double *lp = linv + p * M;
            double sum = 0.0;
            for (int64_t q = 0; q <= p; q++) sum += lp[q] * gt[q];
            xa[p] = sum;
            ra -= sum * u[p];
        }
        r[a] = ra;
        for (int64_t c = 0; c <= a; c++) {
            const double *xc = x + c * M;
            double sum = gaa[c];
            for (int64_t p = 0; p < mt; p++) sum -= xa[p] * xc[p];
            sc[a * N + c] = sum;
        }
    }
    /* S = C C^T in place (lower), z = C^-1 r. */
    for (int64_t a = 0; a < na; a++) {
        double *cr = sc + a * N;
        for (int64_t c = 0; c < a; c++) {
            double sum = cr[c];
            for (int64_t k = 0; k < c; k++) sum -= cr[k] * sc[c * N + k];
            cr[c] = sum * inv[c];
        }
        double sum = cr[a];
        for (int64_t k = 0; k < a; k++) sum -= cr[k] * cr[k];
        if (!(sum > 0.0)) status = 1;
        cr[a] = sqrt(sum);
        inv[a] = 1.0 / cr[a];
        double zs = r[a];
        for (int64_t k = 0; k < a; k++) zs -= cr[k] * z[k];
        z[a] = zs * inv[a];
    }
    for (int64_t i = 0; i < N; i++) {
        if (agent_task != NULL && agent_task[b * N + i] >= 0) {  /* parked: its task's */
            const double held = active == NULL || active[b] ? task_value : 0.0;
            if (out != NULL) out[b * N + i] = held;
            if (out32 != NULL) out32[b * N + i] = (float)held;
            continue;
        }
        double phi = 0.0;
        int on_agent = 0, on_task = 0;
        if (ca[i] && cnt[4 * b + 3]) {
            for (int64_t s = 0; s < T; s++) {
                if (s == i || !ca[s] || ce[s] != ce[i]) continue;
                if (s < N) on_agent = 1; else on_task = 1;
            }
        }
        if (on_agent) {
            phi = agent_value;
        } else if (on_task) {
            phi = task_value;
        } else if (as[i] >= 0) {
            /* y = C^-1 e_k is zero above row k: P_kk = |y|^2, (S^-1 r)_k = y . z. */
            const int64_t k = as[i];
            double pii = 0.0, pv = 0.0;
            for (int64_t a = k; a < na; a++) {
                double sum = a == k ? 1.0 : 0.0;
                for (int64_t c = k; c < a; c++) sum -= sc[a * N + c] * y[c];
                y[a] = sum * inv[a];
                pii += y[a] * y[a];
                pv += y[a] * z[a];
            }
            phi = agent_value - pv / pii;
        }
        if (active != NULL && !active[b]) phi = 0.0;
        if (out != NULL) out[b * N + i] = phi;
        if (out32 != NULL) out32[b * N + i] = (float)phi;
    }
    return status;
}

/* r_IPF of every AGV (IPFGrid.agent_potentials): AGV i's own field at its own cell.
 *
 * Per environment: the sources (AGVs first, then open tasks) on free cells, deduplicated (a
 * source is dropped when an earlier candidate shares its cell). With the kept tasks' block
 * D = G[T, T] = L L^T, X = G[A, T] L^-T, the Schur complement S = G[A, A] - X X^T and
 * r = v_A - X L^-1 v_T, AGV a's value is v_a - (S^-1 r)_a / (S^-1)_aa (the module notes of
 * sim/ipf.py derive it). Tasks move only at resets and claims, so L^-1 and L^-1 v_T are kept
 * in `cache` per environment, with the task cells they were built for: tcache (B, 1 + M)
 * int64 = count, cells; dcache (B, M * M + M) float64 = L^-1 (row-major), L^-1 v_T. A count
 * of -1 marks an empty entry. Everything after that is independent dot products, which
 * pipeline far better than a full Cholesky factor of G[T u A, T u A].
 *
 * An AGV whose cell holds another source reads that source's value (an AGV's if any); an AGV
 * on a fixed cell reads 0. g is the padded Green's function (F + 1) x (F + 1); free_index maps
 * a flat cell to its free index or -1. task_mask (B, M) marks the open tasks, or the claimed
 * ones if mask_is_claimed (NULL: all open). The values go to out (float64) and/or out32
 * (float32), either may be NULL. Optional (NULL to leave out): agent_task (B, N), where
 * an AGV holding a task reads task_value (the reward's parked rule); active (B,), where an
 * inactive environment is skipped and reads 0. Returns 0; 1 if a factor was not positive
 * definite; -1 if scratch memory could not be allocated. */
AGV_WIDE
int agv_ipf(int64_t B, int64_t N, int64_t M, const float *agent_pos, const float *task_pos,
            const uint8_t *task_mask, int64_t mask_is_claimed, const double *g,
            const double *gdiag, int64_t F, const int64_t *free_index, int64_t H, int64_t W,
            double xmin, double ymin, double dx, double dy, double agent_value,
            double task_value, const int64_t *agent_task, const uint8_t *active,
            int64_t *tcache, double *dcache, double *out, float *out32) {
    const int64_t T = N + M, F1 = F + 1, AHEAD = 4;
    /* Entries of G one environment needs: the task block (only when its factor is stale),
     * G[A, T] and the lower triangle of G[A, A] (its diagonal from gdiag, G's diagonal, which
     * stays in cache). */
    const int64_t GT = M * (M + 1) / 2, GA = N * M + N * (N + 1) / 2;
    /* Scratch from a per-thread arena kept between calls (no B-sized malloc and free, and no
     * fresh pages to fault in, on every step). */
    const size_t n64 = (size_t)(3 * B * T + B * N + 4 * B + 1), nd = (size_t)(B * (GT + GA) + 1);
    const size_t small = (size_t)(N * M + N * N + 4 * N + T + M * M + 7);
    unsigned char *arena = arena_reserve(8 * (n64 + nd + small));
    if (arena == NULL) return -1;
    int64_t *cell = (int64_t *)arena;
    int64_t *src = cell + B * T;  /* kept tasks, then AGVs */
    int64_t *aslot = src + B * T;
    int64_t *cnt = aslot + B * N;  /* mt, na, stale, shared */
    /* candidate flags, then shadowed flags: 2 B T bytes in the last B T + 1 slots */
    uint8_t *cand = (uint8_t *)(cnt + 4 * B);
    double *stage = (double *)(cell + n64);
    double *x = stage + nd, *sc = x + N * M, *r = sc + N * N, *z = r + N + 1, *y = z + N + 1;
    double *inv = y + N + 1, *l = inv + T + 1;
    int status = 0;
    /* Pass 1: cells, candidates, kept sources, and whether the cached task factor is stale. */
    for (int64_t b = 0; b < B; b++) {
        int64_t *ce = cell + b * T, *sr = src + b * T, *as = aslot + b * N;
        uint8_t *ca = cand + b * T;
        for (int64_t s = 0; s < T; s++) {
            const float *q = s < N ? agent_pos + (b * N + s) * 2 : task_pos + (b * M + s - N) * 2;
            /* floor, then clip to the grid (a truncation is the floor of values >= 0) */
            const double fx = ((double)q[0] - xmin) / dx, fy = ((double)q[1] - ymin) / dy;
            const int64_t col = fx < 0.0 ? 0 : (fx >= (double)(W - 1) ? W - 1 : (int64_t)fx);
            const int64_t row = fy < 0.0 ? 0 : (fy >= (double)(H - 1) ? H - 1 : (int64_t)fy);
            ce[s] = row * W + col;
            ca[s] = free_index[ce[s]] >= 0
                    && (s < N || task_mask == NULL
                        || (task_mask[b * M + s - N] != 0) != (mask_is_claimed != 0));
        }
        /* A candidate is shadowed by an earlier one (lower index) in its cell: branch-free
         * over the pairs. */
        uint8_t *shadow = ca + B * T;
        int64_t shared = 0;
        for (int64_t s = 0; s < T; s++) {
            int hit = 0;
            for (int64_t e = 0; e < s; e++) hit |= ca[e] & (ce[e] == ce[s]);
            shadow[s] = (uint8_t)(hit & ca[s]);
            shared |= shadow[s];
        }
        int64_t mt = 0, na = 0;
        for (int pass = 0; pass < 2; pass++) {  /* tasks first in src, AGVs after */
            const int64_t lo = pass == 0 ? N : 0, hi = pass == 0 ? T : N;
            for (int64_t s = lo; s < hi; s++) {
                if (s < N) as[s] = -1;
                if (!ca[s] || shadow[s]) continue;
                if (s < N) {
                    as[s] = na;
                    sr[mt + na++] = free_index[ce[s]];
                } else {
                    sr[mt++] = free_index[ce[s]];
                }
            }
        }
        const int64_t *tc = tcache + b * (M + 1);
        int fresh = tc[0] == mt;
        for (int64_t p = 0; p < mt && fresh; p++) fresh = tc[1 + p] == sr[p];
        const int skip = active != NULL && !active[b];
        cnt[4 * b] = mt;
        cnt[4 * b + 1] = skip ? 0 : na;
        cnt[4 * b + 2] = !fresh && !skip;
        cnt[4 * b + 3] = shared;  /* some candidates share a cell */
    }
    /* Pass 2: gather every entry of G needed into `stage`, one loop of independent loads,
     * with each environment's entries prefetched (to L2) AHEAD environments earlier: the
     * entries miss the caches (G is several MiB); this keeps more misses in flight than
     * loads interleaved with the factorizations could. */
    for (int64_t b = 0; b < B + AHEAD; b++) {
        if (b < B) {
            const int64_t *sp = src + b * T, mt = cnt[4 * b], na = cnt[4 * b + 1];
            if (cnt[4 * b + 2])
                for (int64_t p = 0; p < mt; p++)
                    for (int64_t q = 0; q <= p; q++) __builtin_prefetch(g + sp[p] * F1 + sp[q], 0, 2);
            for (int64_t a = 0; a < na; a++) {
                const double *grow = g + sp[mt + a] * F1;
                for (int64_t q = 0; q < mt + a; q++) __builtin_prefetch(grow + sp[q], 0, 2);
            }
        }
        const int64_t e = b - AHEAD;
        if (e < 0) continue;
        const int64_t *sr = src + e * T, mt = cnt[4 * e], na = cnt[4 * e + 1];
        double *st = stage + e * (GT + GA);
        if (cnt[4 * e + 2])
            for (int64_t p = 0; p < mt; p++)
                for (int64_t q = 0; q <= p; q++) *st++ = g[sr[p] * F1 + sr[q]];
        st = stage + e * (GT + GA) + GT;
        for (int64_t a = 0; a < na; a++) {
            const double *grow = g + sr[mt + a] * F1;
            for (int64_t q = 0; q < mt + a; q++) *st++ = grow[sr[q]];
            *st++ = gdiag[sr[mt + a]];
        }
    }
    /* Pass 3: factorizations and values. */
    for (int64_t b = 0; b < B; b++) {
        const int64_t mt = cnt[4 * b], na = cnt[4 * b + 1];
#define IPF_VALUES(n, m, nt, nagents)                                                         \
    ipf_values(n, m, nt, nagents, b, T, cell, src, aslot, cand, cnt, tcache, dcache, stage,   \
               GT, GA, l, inv, x, sc, r, z, y, agent_value, task_value, agent_task, active,    \
               out, out32)
        if (N == 6 && M == 6 && mt == 6 && na == 6) status |= IPF_VALUES(6, 6, 6, 6);
        else if (N == 3 && M == 3 && mt == 3 && na == 3) status |= IPF_VALUES(3, 3, 3, 3);
        else status |= IPF_VALUES(N, M, mt, na);
#undef IPF_VALUES
    }
    return status;
}

typedef double ipf_v2 __attribute__((vector_size(16)));

/* Two doubles from any (8-byte aligned) address. */
static inline ipf_v2 ipf_load2(const double *p) {
    ipf_v2 v;
    memcpy(&v, p, sizeof v);
    return v;
}

/* x . y over n doubles in pairs of lanes, four running sums of two (SSE2 on x86-64). */
static inline double ipf_dot_v2(const double *x, const double *y, int64_t n) {
    ipf_v2 s0 = {0.0, 0.0}, s1 = s0, s2 = s0, s3 = s0;
    int64_t q = 0;
    for (; q + 8 <= n; q += 8) {
        s0 += ipf_load2(x + q) * ipf_load2(y + q);
        s1 += ipf_load2(x + q + 2) * ipf_load2(y + q + 2);
        s2 += ipf_load2(x + q + 4) * ipf_load2(y + q + 4);
        s3 += ipf_load2(x + q + 6) * ipf_load2(y + q + 6);
    }
    s0 = (s0 + s1) + (s2 + s3);
    double g = s0[0] + s0[1];
    for (; q < n; q++) g += x[q] * y[q];
    return g;
}

/* Entries of the Green's function from the separator tree (sim/ipf/hierarchy.py,
 * SeparatorTree.entries, the torch reference): out[b, j, k] = G[rows[b, j], cols[b, k]].
 *
 * Per cell c (a free index in [0, F]; F reads 0) the tree keeps ycat[c] (W doubles: every
 * level's vector side by side, level l in [offsets[l], offsets[l + 1])) and path[c] (L ids:
 * its domain per level, a number of its own where it lies in none). Two cells share the
 * first `s` levels (their common ancestors) and G adds y . y over exactly those: one dot
 * product of length offsets[s] (the levels are stored in order). Cells in one leaf add the
 * leaf's dense block: leaf_values[leaf_offset[l] + local[a] * leaf_size[l] + local[c]].
 * sym != 0: rows and cols are the same cells (J == K) and only j <= k is computed. */
AGV_WIDE
int agv_ipf_tree_entries(int64_t B, int64_t J, int64_t K, const int64_t *rows,
                         const int64_t *cols, int64_t sym, const double *ycat, int64_t W,
                         const int64_t *path, int64_t L, const int64_t *offsets,
                         const int64_t *leaf_id, const int64_t *leaf_local,
                         const int64_t *leaf_size, const int64_t *leaf_offset,
                         const double *leaf_values, double *out) {
    for (int64_t b = 0; b < B; b++) {
        const int64_t *rb = rows + b * J, *cb = (sym ? rows + b * J : cols + b * K);
        double *ob = out + b * J * K;
        if (b + 1 < B) {  /* the next environment's vectors, fetched while this one runs */
            const int64_t *nr = rows + (b + 1) * J;
            for (int64_t j = 0; j < J; j++)
                for (int64_t q = 0; q < W; q += 8) __builtin_prefetch(ycat + nr[j] * W + q, 0, 2);
        }
        for (int64_t j = 0; j < J; j++) {
            const int64_t a = rb[j];
            const double *ya = ycat + a * W;
            const int64_t *pa = path + a * L;
            const int64_t la = leaf_id[a];
            for (int64_t k = sym ? j : 0; k < K; k++) {
                const int64_t c = cb[k];
                const int64_t *pc = path + c * L;
                int64_t s = 0;
                while (s < L && pa[s] == pc[s]) s++;
                const int64_t n = offsets[s];
                double g = ipf_dot_v2(ya, ycat + c * W, n);
                if (la >= 0 && la == leaf_id[c])
                    g += leaf_values[leaf_offset[la] + leaf_local[a] * leaf_size[la]
                                     + leaf_local[c]];
                ob[j * K + k] = g;
                if (sym) ob[k * K + j] = g;
            }
        }
    }
    return 0;
}

/* One level's part of a Gram block: acc[i * ld + k] += x_i . x_k (k >= i, 0 <= i, k < g) for
 * the g rows x_i = ycat + cells[i] * W + lo of length n. Every pair's dot product is one
 * four-lane running sum over q = 0, 4, 8, ..., its lanes added as (l0 + l1) + (l2 + l3), then
 * the last n % 4 terms in order: the same operations in the same order in the 2 x 4 tiles and
 * in the edge loop, so a pair's value never depends on the tile it fell in (nor on the other
 * cells of the call), and the AVX2 and the default clone agree bit for bit (the default one
 * does each four-lane operation as two SSE2 ones). */
typedef double ipf_v4 __attribute__((vector_size(32)));

static inline __attribute__((always_inline)) ipf_v4 ipf_load4(const double *p) {
    ipf_v4 v;
    memcpy(&v, p, sizeof v);
    return v;
}

static inline __attribute__((always_inline)) double ipf_lanes4(ipf_v4 s) {
    return (s[0] + s[1]) + (s[2] + s[3]);
}

static inline __attribute__((always_inline)) double ipf_dot_pair(const double *x,
                                                                const double *y, int64_t n) {
    ipf_v4 s = {0.0, 0.0, 0.0, 0.0};
    int64_t q = 0;
    for (; q + 4 <= n; q += 4) s += ipf_load4(x + q) * ipf_load4(y + q);
    double g = ipf_lanes4(s);
    for (; q < n; q++) g += x[q] * y[q];
    return g;
}

static inline __attribute__((always_inline)) void ipf_gram_level(
    double *restrict acc, int64_t ld, const int64_t *cells, int64_t g, const double *ycat,
    int64_t W, int64_t lo, int64_t n) {
    int64_t i = 0;
    for (; i + 2 <= g; i += 2) {
        const double *x0 = ycat + cells[i] * W + lo, *x1 = ycat + cells[i + 1] * W + lo;
        int64_t k = i;
        for (; k + 4 <= g; k += 4) {
            const double *y0 = ycat + cells[k] * W + lo, *y1 = ycat + cells[k + 1] * W + lo;
            const double *y2 = ycat + cells[k + 2] * W + lo, *y3 = ycat + cells[k + 3] * W + lo;
            ipf_v4 a00 = {0.0, 0.0, 0.0, 0.0}, a01 = a00, a02 = a00, a03 = a00;
            ipf_v4 a10 = a00, a11 = a00, a12 = a00, a13 = a00;
            int64_t q = 0;
            for (; q + 4 <= n; q += 4) {
                const ipf_v4 u0 = ipf_load4(x0 + q), u1 = ipf_load4(x1 + q);
                const ipf_v4 v0 = ipf_load4(y0 + q), v1 = ipf_load4(y1 + q);
                const ipf_v4 v2 = ipf_load4(y2 + q), v3 = ipf_load4(y3 + q);
                a00 += u0 * v0; a01 += u0 * v1; a02 += u0 * v2; a03 += u0 * v3;
                a10 += u1 * v0; a11 += u1 * v1; a12 += u1 * v2; a13 += u1 * v3;
            }
            double r0[4] = {ipf_lanes4(a00), ipf_lanes4(a01), ipf_lanes4(a02), ipf_lanes4(a03)};
            double r1[4] = {ipf_lanes4(a10), ipf_lanes4(a11), ipf_lanes4(a12), ipf_lanes4(a13)};
            for (; q < n; q++) {
                const double t0 = x0[q], t1 = x1[q];
                const double w[4] = {y0[q], y1[q], y2[q], y3[q]};
                for (int c = 0; c < 4; c++) {
                    r0[c] += t0 * w[c];
                    r1[c] += t1 * w[c];
                }
            }
            double *o0 = acc + i * ld + k, *o1 = acc + (i + 1) * ld + k;
            for (int c = 0; c < 4; c++) {
                o0[c] += r0[c];
                if (k + c >= i + 1) o1[c] += r1[c];
            }
        }
        for (; k < g; k++) {
            const double *y = ycat + cells[k] * W + lo;
            acc[i * ld + k] += ipf_dot_pair(x0, y, n);
            if (k >= i + 1) acc[(i + 1) * ld + k] += ipf_dot_pair(x1, y, n);
        }
    }
    for (; i < g; i++) {
        const double *x = ycat + cells[i] * W + lo;
        for (int64_t k = i; k < g; k++)
            acc[i * ld + k] += ipf_dot_pair(x, ycat + cells[k] * W + lo, n);
    }
}

/* The unloaded AGVs' blocks of IPFGrid.lifelong_potentials (its torch code is the reference),
 * per environment: with the open pickups' factor Li = L_D^-1 (linv, (B, Q, Q), lower,
 * row-major) and u = Li v_P, X = G[A, P] Li^T (gap, (B, N, Q): gap[b, j, q] = G[a_j, p_q]),
 * schur = G[A, A] - X X^T ((B, N, N) from gaa) and r = v_A - X u ((B, N) from va). Li is
 * triangular and schur symmetric, so half of each product is skipped. Returns 0; -1 if
 * scratch memory failed. */
AGV_WIDE
int agv_ipf_lifelong_block(int64_t B, int64_t N, int64_t Q, const double *gap,
                           const double *linv, const double *u, const double *gaa,
                           const double *va, double *schur, double *r) {
    double *x = arena_reserve(8 * (size_t)(N * Q + N * N) + 8 * (size_t)N);
    if (x == NULL) return -1;
    double *acc = x + N * Q;
    int64_t *ids = (int64_t *)(acc + N * N);
    for (int64_t j = 0; j < N; j++) ids[j] = j;
    for (int64_t b = 0; b < B; b++) {
        const double *gb = gap + b * N * Q, *lb = linv + b * Q * Q, *ub = u + b * Q;
        for (int64_t q = 0; q < Q; q++) {  /* X[:, q] = G[A, P[0..q]] . Li[q, 0..q] */
            const double *lq = lb + q * Q;
            const int64_t n = q + 1;
            int64_t j = 0;
            for (; j + 4 <= N; j += 4) {
                const double *g0 = gb + j * Q, *g1 = g0 + Q, *g2 = g1 + Q, *g3 = g2 + Q;
                ipf_v4 s0 = {0.0, 0.0, 0.0, 0.0}, s1 = s0, s2 = s0, s3 = s0;
                int64_t p = 0;
                for (; p + 4 <= n; p += 4) {
                    const ipf_v4 w = ipf_load4(lq + p);
                    s0 += ipf_load4(g0 + p) * w;
                    s1 += ipf_load4(g1 + p) * w;
                    s2 += ipf_load4(g2 + p) * w;
                    s3 += ipf_load4(g3 + p) * w;
                }
                double t[4] = {ipf_lanes4(s0), ipf_lanes4(s1), ipf_lanes4(s2), ipf_lanes4(s3)};
                for (; p < n; p++) {
                    t[0] += g0[p] * lq[p];
                    t[1] += g1[p] * lq[p];
                    t[2] += g2[p] * lq[p];
                    t[3] += g3[p] * lq[p];
                }
                for (int c = 0; c < 4; c++) x[(j + c) * Q + q] = t[c];
            }
            for (; j < N; j++) x[j * Q + q] = ipf_dot_pair(gb + j * Q, lq, n);
        }
        for (int64_t m = 0; m < N * N; m++) acc[m] = 0.0;
        ipf_gram_level(acc, N, ids, N, x, Q, 0, Q);
        const double *ab = gaa + b * N * N;
        double *sb = schur + b * N * N;
        for (int64_t i = 0; i < N; i++)
            for (int64_t k = i; k < N; k++) {
                const double v = ab[i * N + k] - acc[i * N + k];
                sb[i * N + k] = v;
                sb[k * N + i] = v;
            }
        for (int64_t j = 0; j < N; j++)
            r[b * N + j] = va[b * N + j] - ipf_dot_pair(x + j * Q, ub, Q);
    }
    return 0;
}

/* The symmetric block G[rows[b, j], rows[b, k]] (out, (B, J, J)) from the separator tree,
 * as agv_ipf_tree_entries with sym, in register tiles: per environment the cells are put in
 * the tree's depth-first order (rank, SeparatorTree._dfs_rank: each domain of each level and
 * each leaf is a run of consecutive places), the runs of each level add their Gram block of
 * that level's vectors, level by level, and the pairs in one leaf add its dense block. A
 * pair's levels are the common prefix of its paths, the least of the prefixes of the
 * consecutive cells between them in that order. Returns 0; -1 if scratch memory failed. */
AGV_WIDE
int agv_ipf_tree_gram(int64_t B, int64_t J, const int64_t *rows, const double *ycat, int64_t W,
                      const int64_t *path, int64_t L, const int64_t *offsets,
                      const int64_t *rank, const int64_t *leaf_id, const int64_t *leaf_local,
                      const int64_t *leaf_size, const int64_t *leaf_offset,
                      const double *leaf_values, double *out) {
    double *acc = arena_reserve(8 * (size_t)(J * J) + 8 * (size_t)(3 * J + 1));
    if (acc == NULL) return -1;
    int64_t *perm = (int64_t *)(acc + J * J), *sc = perm + J, *lcp = sc + J;
    for (int64_t b = 0; b < B; b++) {
        const int64_t *rb = rows + b * J;
        for (int64_t j = 0; j < J; j++) {  /* insertion sort by rank, ties in index order */
            const int64_t key = rank[rb[j]];
            int64_t m = j;
            while (m > 0 && rank[rb[perm[m - 1]]] > key) {
                perm[m] = perm[m - 1];
                m--;
            }
            perm[m] = j;
        }
        for (int64_t m = 0; m < J; m++) sc[m] = rb[perm[m]];
        for (int64_t m = 0; m + 1 < J; m++) {
            const int64_t *pa = path + sc[m] * L, *pc = path + sc[m + 1] * L;
            int64_t s = 0;
            while (s < L && pa[s] == pc[s]) s++;
            lcp[m] = s;
        }
        for (int64_t m = 0; m < J * J; m++) acc[m] = 0.0;
        for (int64_t l = 0; l < L; l++) {
            const int64_t lo = offsets[l], n = offsets[l + 1] - lo;
            for (int64_t m = 0; m < J;) {
                int64_t e = m;
                while (e + 1 < J && lcp[e] > l) e++;
                ipf_gram_level(acc + m * J + m, J, sc + m, e - m + 1, ycat, W, lo, n);
                m = e + 1;
            }
        }
        for (int64_t i = 0; i < J; i++) {  /* one leaf's cells are consecutive too */
            const int64_t li = leaf_id[sc[i]];
            if (li < 0) continue;
            const double *lv = leaf_values + leaf_offset[li] + leaf_local[sc[i]] * leaf_size[li];
            for (int64_t k = i; k < J && leaf_id[sc[k]] == li; k++)
                acc[i * J + k] += lv[leaf_local[sc[k]]];
        }
        double *ob = out + b * J * J;
        for (int64_t i = 0; i < J; i++)
            for (int64_t k = i; k < J; k++) {
                const double g = acc[i * J + k];
                ob[perm[i] * J + perm[k]] = g;
                ob[perm[k] * J + perm[i]] = g;
            }
    }
    return 0;
}

/* The Cholesky factor of the SPD n x n block u (row-major, read from its upper triangle) in
 * place: u = C^T (upper), inv[k] = 1 / C_kk. Returns 1
 * when the block is not positive definite. */
static inline __attribute__((always_inline)) int ipf_cholesky(int64_t n, double *restrict u,
                                                             double *restrict inv) {
    int status = 0;
    for (int64_t k = 0; k < n; k++) {
        double *uk = u + k * n;
        if (!(uk[k] > 0.0)) status = 1;
        const double root = sqrt(uk[k]), rk = 1.0 / root;
        uk[k] = root;
        inv[k] = rk;
        for (int64_t j = k + 1; j < n; j++) uk[j] *= rk;
        for (int64_t i = k + 1; i < n; i++) {
            const double f = uk[i];
            double *ui = u + i * n;
            for (int64_t j = i; j < n; j++) ui[j] -= f * uk[j];
        }
    }
    return status;
}

/* The factor and inverse of the SPD n x n block `a` (row-major, read from its upper triangle)
 * in vectorizable row operations: u = C^T (upper, row-major, in place of a) with C C^T = a,
 * inv[k] = 1 / C_kk, and y = C^-1 (lower, row-major; above the diagonal undefined). Then the
 * column sums d[c] = sum_a y[a][c]^2 = (a^-1)_cc. Returns 1 when the block is not positive
 * definite. */
static inline __attribute__((always_inline)) int ipf_factor_inverse(
    int64_t n, double *restrict u, double *restrict y, double *restrict inv, double *restrict d) {
    const int status = ipf_cholesky(n, u, inv);
    for (int64_t c = 0; c < n; c++) d[c] = 0.0;
    for (int64_t a = 0; a < n; a++) {
        double *ya = y + a * n;
        for (int64_t c = 0; c < a; c++) ya[c] = 0.0;
        for (int64_t k = 0; k < a; k++) {  /* C[a][k] = u[k][a] */
            const double f = u[k * n + a];
            const double *yk = y + k * n;
            for (int64_t c = 0; c <= k; c++) ya[c] -= f * yk[c];
        }
        for (int64_t c = 0; c < a; c++) ya[c] *= inv[a];
        ya[a] = inv[a];
        for (int64_t c = 0; c <= a; c++) d[c] += ya[c] * ya[c];
    }
    return status;
}

/* Factors of a batch of SPD blocks (B, n, n), row-major, read from their upper triangles:
 * y[b] = C^-1 (lower, row-major, zeros above the diagonal) where C C^T = blocks[b] (what
 * TaskBlockCache keeps, without LAPACK's per-matrix overhead at these sizes). Returns 0; 1 if
 * a block was not positive definite; -1 if scratch memory failed. */
AGV_WIDE
int agv_ipf_inverse_factors(int64_t B, int64_t n, const double *blocks, double *y) {
    double *u = arena_reserve(8 * (size_t)(n * n + 2 * n));
    if (u == NULL) return -1;
    double *inv = u + n * n, *d = inv + n;
    int status = 0;
    for (int64_t b = 0; b < B; b++) {
        double *yb = y + b * n * n;
        memcpy(u, blocks + b * n * n, 8 * (size_t)(n * n));
        status |= ipf_factor_inverse(n, u, yb, inv, d);
        for (int64_t a = 0; a < n; a++)
            for (int64_t c = a + 1; c < n; c++) yb[a * n + c] = 0.0;
    }
    return status;
}

/* perm: the AGVs that are not targets first, then the targets (candidates with loaded ==
 * want), each group in index order; returns the number of targets. */
static inline __attribute__((always_inline)) int64_t ipf_targets_last(
    int64_t N, const uint8_t *ld, const uint8_t *ac, int want, int64_t *perm) {
    int64_t k = 0, m = 0;
    for (int64_t i = 0; i < N; i++)
        if (!(ac[i] && (ld[i] != 0) == want)) perm[k++] = i;
    for (int64_t i = 0; i < N; i++)
        if (ac[i] && (ld[i] != 0) == want) perm[k++] = i, m++;
    return m;
}

/* u = P a P^T (row-major n x n): u[i][j] = a[perm[i]][perm[j]]. */
static inline __attribute__((always_inline)) void ipf_permuted(
    int64_t n, const double *a, const int64_t *perm, double *restrict u) {
    for (int64_t i = 0; i < n; i++) {
        const double *ai = a + perm[i] * n;
        double *ui = u + i * n;
        for (int64_t j = 0; j < n; j++) ui[j] = ai[perm[j]];
    }
}

/* x = C^-1 x in place for the n x k right-hand sides x (row-major), C = u^T from
 * ipf_cholesky: row k is final once the rows above it are, then leaves the rows below. */
static inline __attribute__((always_inline)) void ipf_forward(int64_t n, const double *u,
                                                             const double *inv,
                                                             double *restrict x, int64_t k) {
    for (int64_t a = 0; a < n; a++) {
        double *xa = x + a * k;
        for (int64_t t = 0; t < k; t++) xa[t] *= inv[a];
        const double *ua = u + a * n;
        for (int64_t c = a + 1; c < n; c++) {
            const double f = ua[c];
            double *xc = x + c * k;
            for (int64_t t = 0; t < k; t++) xc[t] -= f * xa[t];
        }
    }
}

/* The trailing m x m block of Y = C^-1 (yt, lower, row-major: the inverse of C's trailing
 * block, since C is lower triangular), its column sums of squares d[t] = (A^-1)_tt over the
 * last m places, and p[t] = (Y^T z)_t there for z = C^-1 r (zf, the full forward solve):
 * (A^-1 r)_t. */
static inline __attribute__((always_inline)) void ipf_trailing(
    int64_t n, int64_t m, const double *u, const double *inv, const double *zf,
    double *restrict yt, double *restrict d, double *restrict p) {
    const int64_t o = n - m;
    for (int64_t c = 0; c < m; c++) d[c] = p[c] = 0.0;
    for (int64_t a = 0; a < m; a++) {
        double *ya = yt + a * m;
        for (int64_t c = 0; c < m; c++) ya[c] = 0.0;
        for (int64_t k = 0; k < a; k++) {  /* C[o + a][o + k] = u[o + k][o + a] */
            const double f = u[(o + k) * n + o + a];
            const double *yk = yt + k * m;
            for (int64_t c = 0; c <= k; c++) ya[c] -= f * yk[c];
        }
        for (int64_t c = 0; c < a; c++) ya[c] *= inv[o + a];
        ya[a] = inv[o + a];
        const double za = zf[o + a];
        for (int64_t c = 0; c <= a; c++) {
            d[c] += ya[c] * ya[c];
            p[c] += ya[c] * za;
        }
    }
}

/* The dense part of IPFGrid.lifelong_potentials (the torch code there is the reference), one
 * environment at a time, after the entries of G are gathered:
 *
 * - unloaded AGV i: with S = C C^T (schur, (B, N, N), the Schur complement of the open
 *   pickups' block), Y = C^-1, z = Y r: phi_i = v_i - (Y[:, i] . z) / |Y[:, i]|^2;
 * - loaded AGV i: with G[A, A] = C C^T (gaa), Y = C^-1, e = Y v_A, w = Y G[A, d_i] (column i
 *   of gad, (B, N, N), gad[b, j, i] = G[a_j, d_i]), s = gamma_i - |w|^2 (1 where d_src is
 *   0), h = Y[:, i] . w: phi_i = v_i - (Y[:, i] . e + h (w . e - v_d) / s)
 *   / (|Y[:, i]|^2 + h^2 / s);
 *
 * then the cell rules: another candidate AGV on i's cell (cells ca, candidates acand) gives
 * agent_value, else its own task_value source (its drop-off cd when loaded and dfree, an open
 * pickup cp / popen when not) gives task_value; a non-candidate AGV and an environment that
 * is not active (NULL: all are) read 0. schur and r may be NULL when no AGV is unloaded, gad
 * and gamma when none is loaded. Returns 0; 1 if a block was not positive definite; -1 if
 * scratch memory failed. */
AGV_WIDE
int agv_ipf_lifelong(int64_t B, int64_t N, int64_t Q, const double *schur, const double *r,
                     const double *gaa, const double *gad, const double *gamma,
                     const double *va, const uint8_t *loaded, const uint8_t *dsrc,
                     const int64_t *ca, const int64_t *cp, const int64_t *cd,
                     const uint8_t *acand, const uint8_t *popen, const uint8_t *dfree,
                     const uint8_t *active, double agent_value, double task_value,
                     double *out) {
    double *u = arena_reserve(8 * (size_t)(3 * N * N + 8 * N + 1) + 8 * (size_t)N);
    if (u == NULL) return -1;
    double *yt = u + N * N, *wl = yt + N * N, *inv = wl + N * N;
    double *d = inv + N, *z = d + N, *rp = z + N, *ww = rp + N, *hv = ww + N, *hh = hv + N;
    int64_t *perm = (int64_t *)(hh + N);
    int status = 0;
    for (int64_t b = 0; b < B; b++) {
        double *ob = out + b * N;
        for (int64_t i = 0; i < N; i++) ob[i] = 0.0;
        if (active != NULL && !active[b]) continue;
        const uint8_t *ld = loaded + b * N, *ds = dsrc + b * N, *ac = acand + b * N;
        const double *vb = va + b * N;
        /* the AGVs whose potential a factor serves go last (perm), so that only the trailing
         * block of its inverse is needed: m targets among N */
        int64_t m = 0;
        if (schur != NULL) {
            m = ipf_targets_last(N, ld, ac, 0, perm);
            if (m > 0) {
                const double *sb = schur + b * N * N, *rb = r + b * N;
                ipf_permuted(N, sb, perm, u);
                status |= ipf_cholesky(N, u, inv);
                for (int64_t a = 0; a < N; a++) rp[a] = rb[perm[a]];
                ipf_forward(N, u, inv, rp, 1);  /* z = C^-1 r, in place */
                ipf_trailing(N, m, u, inv, rp, yt, d, z);  /* d = diag(S^-1), z = S^-1 r */
                for (int64_t t = 0; t < m; t++) {
                    const int64_t i = perm[N - m + t];
                    ob[i] = vb[i] - z[t] / d[t];
                }
            }
        }
        m = gad != NULL ? ipf_targets_last(N, ld, ac, 1, perm) : 0;
        if (m > 0) {
            ipf_permuted(N, gaa + b * N * N, perm, u);
            status |= ipf_cholesky(N, u, inv);
            for (int64_t a = 0; a < N; a++) rp[a] = vb[perm[a]];
            ipf_forward(N, u, inv, rp, 1);  /* e = C^-1 v_A */
            /* W = C^-1 G[A, d_targets]: column t is G[a, d_i] over the permuted AGVs a */
            const double *gb = gad + b * N * N;
            for (int64_t a = 0; a < N; a++)
                for (int64_t t = 0; t < m; t++) wl[a * m + t] = gb[perm[a] * N + perm[N - m + t]];
            ipf_forward(N, u, inv, wl, m);
            for (int64_t t = 0; t < m; t++) ww[t] = hv[t] = 0.0;
            for (int64_t a = 0; a < N; a++) {
                const double *wa = wl + a * m;
                const double ea = rp[a];
                for (int64_t t = 0; t < m; t++) {
                    ww[t] += wa[t] * wa[t];
                    hv[t] += wa[t] * ea;
                }
            }
            ipf_trailing(N, m, u, inv, rp, yt, d, z);  /* d = diag(Q), z = (Q v_A) */
            /* h_t = Y[:, i_t] . w_t over the trailing rows (Y is zero above its diagonal) */
            for (int64_t t = 0; t < m; t++) hh[t] = 0.0;
            for (int64_t a = 0; a < m; a++) {
                const double *ya = yt + a * m;
                const double *wa = wl + (N - m + a) * m;
                for (int64_t t = 0; t <= a; t++) hh[t] += ya[t] * wa[t];
            }
            for (int64_t t = 0; t < m; t++) {
                const int64_t i = perm[N - m + t];
                const double sv = ds[i] ? gamma[b * N + i] - ww[t] : 1.0;
                const double vd = ds[i] ? task_value : 0.0;
                const double pii = d[t] + hh[t] * hh[t] / sv;
                ob[i] = vb[i] - (z[t] + hh[t] * (hv[t] - vd) / sv) / pii;
            }
        }
        const int64_t *cab = ca + b * N, *cpb = cp + b * Q, *cdb = cd + b * N;
        const uint8_t *pob = popen + b * Q, *dfb = dfree + b * N;
        for (int64_t i = 0; i < N; i++) {
            if (!ac[i]) {
                ob[i] = 0.0;
                continue;
            }
            int on_other = 0, on_own = 0;
            for (int64_t j = 0; j < N; j++)
                on_other |= j != i && ac[j] && cab[j] == cab[i];
            if (ld[i]) {
                on_own = cdb[i] == cab[i] && dfb[i];
            } else {
                for (int64_t q = 0; q < Q; q++) on_own |= pob[q] && cpb[q] == cab[i];
            }
            if (on_other) ob[i] = agent_value;
            else if (on_own) ob[i] = task_value;
        }
    }
    return status;
}

/* Entries of G from a table of its columns (IPFGrid._column_table: table[c * width + k] =
 * G[c, cell k]): out1[b, j, q] = table[rows[b, j], w1[b, q]] and out2[b, j, i] =
 * table[rows[b, j], w2[b, i]], both read from one pass over the AGVs' rows, each row
 * prefetched a few AGVs ahead (the rows miss the caches: the table spans tens of MiB).
 * K1 or K2 may be 0 (w and out NULL). */
int agv_ipf_gather_rows(int64_t B, int64_t N, int64_t K1, int64_t K2, const double *table,
                        int64_t width, const int64_t *rows, const int64_t *w1,
                        const int64_t *w2, double *out1, double *out2) {
    const int64_t AHEAD = 6, total = B * N;
    for (int64_t t = 0; t < total + AHEAD; t++) {
        if (t + AHEAD < total) {
            const double *ahead = table + rows[t + AHEAD] * width;
            for (int64_t k = 0; k < width; k += 8) __builtin_prefetch(ahead + k, 0, 1);
        }
        if (t >= total) break;
        const int64_t b = t / N;
        const double *row = table + rows[t] * width;
        if (K1 > 0) {
            const int64_t *wb = w1 + b * K1;
            double *o = out1 + t * K1;
            for (int64_t q = 0; q < K1; q++) o[q] = row[wb[q]];
        }
        if (K2 > 0) {
            const int64_t *wb = w2 + b * K2;
            double *o = out2 + t * K2;
            for (int64_t q = 0; q < K2; q++) o[q] = row[wb[q]];
        }
    }
    return 0;
}

/* The sources of IPFGrid.lifelong_potentials (its torch code is the reference), per
 * environment, from the cells ca (B, N), cp (B, Q), cd (B, N) and their free indices fa, fp,
 * fd (F: a fixed cell): candidate AGVs (acand: on a free cell), kept AGVs (no earlier
 * candidate in the cell), open pickups (popen: open and on a free cell), kept pickups (open,
 * no candidate AGV in the cell, no earlier such pickup in it) and drop-off sources (dsrc:
 * loaded, on a free cell, no candidate AGV in it). Writes the free indices of the kept
 * sources (F for the others) to f_a, f_p, f_d and the AGVs' values to va. */
int agv_ipf_lifelong_sources(int64_t B, int64_t N, int64_t Q, int64_t F, const int64_t *ca,
                             const int64_t *cp, const int64_t *cd, const int64_t *fa,
                             const int64_t *fp, const int64_t *fd, const uint8_t *pickup_open,
                             const uint8_t *loaded, double agent_value, int64_t *f_a,
                             int64_t *f_p, int64_t *f_d, double *va, uint8_t *acand,
                             uint8_t *popen, uint8_t *dsrc) {
    for (int64_t b = 0; b < B; b++) {
        const int64_t *cab = ca + b * N, *cpb = cp + b * Q, *cdb = cd + b * N;
        const int64_t *fab = fa + b * N, *fpb = fp + b * Q, *fdb = fd + b * N;
        uint8_t *ac = acand + b * N, *po = popen + b * Q, *ds = dsrc + b * N;
        for (int64_t i = 0; i < N; i++) ac[i] = fab[i] < F;
        for (int64_t i = 0; i < N; i++) {
            int shadow = 0, under = 0;
            for (int64_t j = 0; j < N; j++) {
                shadow |= j < i && ac[j] && cab[j] == cab[i];
                under |= ac[j] && cab[j] == cdb[i];
            }
            const int kept = ac[i] && !shadow;
            f_a[b * N + i] = kept ? fab[i] : F;
            va[b * N + i] = kept ? agent_value : 0.0;
            ds[i] = loaded[b * N + i] && fdb[i] < F && !under;
            f_d[b * N + i] = ds[i] ? fdb[i] : F;
        }
        for (int64_t q = 0; q < Q; q++) {
            po[q] = pickup_open[b * Q + q] && fpb[q] < F;
            int under = 0;
            for (int64_t j = 0; j < N; j++) under |= ac[j] && cab[j] == cpb[q];
            f_p[b * Q + q] = po[q] && !under ? fpb[q] : F;  /* a candidate, not yet kept */
        }
        for (int64_t q = 0; q < Q; q++) {  /* an earlier candidate in the cell shadows it */
            if (f_p[b * Q + q] == F) continue;
            for (int64_t r = 0; r < q; r++)
                if (f_p[b * Q + r] != F && cpb[r] == cpb[q]) {
                    f_p[b * Q + q] = F;
                    break;
                }
        }
    }
    return 0;
}
