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
int agv_ipf_tree_entries(int64_t B, int64_t J, int64_t K, const int64_t *rows,
                         const int64_t *cols, int64_t sym, const double *ycat, int64_t W,
                         const int64_t *path, int64_t L, const int64_t *offsets,
                         const int64_t *leaf_id, const int64_t *leaf_local,
                         const int64_t *leaf_size, const int64_t *leaf_offset,
                         const double *leaf_values, double *out) {
    for (int64_t b = 0; b < B; b++) {
        const int64_t *rb = rows + b * J, *cb = (sym ? rows + b * J : cols + b * K);
        double *ob = out + b * J * K;
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
                const double *yc = ycat + c * W;
                double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
                int64_t q = 0;
                for (; q + 4 <= n; q += 4) {
                    s0 += ya[q] * yc[q];
                    s1 += ya[q + 1] * yc[q + 1];
                    s2 += ya[q + 2] * yc[q + 2];
                    s3 += ya[q + 3] * yc[q + 3];
                }
                for (; q < n; q++) s0 += ya[q] * yc[q];
                double g = (s0 + s1) + (s2 + s3);
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
