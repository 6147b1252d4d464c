/* Fused CPU kernels of the AGV simulator (see sim/native.py, which builds and loads them).
 *
 * Each kernel loops over the B environments in C and does, per environment, what the torch
 * reference in sim/core.py and sim/ipf.py does with some forty batched tensor operations. The
 * torch code stays the definition; tests/sim/test_native.py checks both agree.
 *
 * Layouts are torch's contiguous row-major ones: positions (B, N, 2) float32, bool tensors as
 * one byte per entry, indices int64. Nothing here allocates per environment.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define INF_F ((float)INFINITY)

/* A per-thread scratch buffer that only grows (released at exit). */
static __thread unsigned char *arena_buf = NULL;
static __thread size_t arena_len = 0;

static void *arena_reserve(size_t bytes) {
    if (bytes > arena_len) {
        free(arena_buf);
        arena_buf = malloc(bytes);
        arena_len = arena_buf ? bytes : 0;
    }
    return arena_buf;
}
#define INF_BITS 0x7f800000u

/* Sort keys: a non-negative float's bit pattern orders like the float (+inf last), so
 * (bits(d) << 32 | j) orders by distance, then by index: a stable sort. */
static inline uint64_t sort_key(float d, int64_t j) {
    uint32_t bits;
    memcpy(&bits, &d, sizeof bits);
    return ((uint64_t)bits << 32) | (uint64_t)j;
}

#define CSWAP(a, b) do { const uint64_t x_ = (a), y_ = (b); (a) = x_ < y_ ? x_ : y_; \
                         (b) = x_ < y_ ? y_ : x_; } while (0)

/* Sort n keys ascending: optimal networks for n <= 4 (5 exchanges) and n <= 8 (19) on keys
 * padded with the largest key, held in registers; insertion for larger n. */
static inline __attribute__((always_inline)) void sort_keys(uint64_t *key, int64_t n) {
    if (n <= 4) {
        uint64_t k0 = key[0], k1 = n > 1 ? key[1] : UINT64_MAX;
        uint64_t k2 = n > 2 ? key[2] : UINT64_MAX, k3 = n > 3 ? key[3] : UINT64_MAX;
        CSWAP(k0, k1); CSWAP(k2, k3);
        CSWAP(k0, k2); CSWAP(k1, k3);
        CSWAP(k1, k2);
        key[0] = k0; key[1] = k1; key[2] = k2; key[3] = k3;
        return;
    }
    if (n <= 8) {
        uint64_t k[8];
        for (int64_t j = 0; j < 8; j++) k[j] = j < n ? key[j] : UINT64_MAX;
        CSWAP(k[0], k[2]); CSWAP(k[1], k[3]); CSWAP(k[4], k[6]); CSWAP(k[5], k[7]);
        CSWAP(k[0], k[4]); CSWAP(k[1], k[5]); CSWAP(k[2], k[6]); CSWAP(k[3], k[7]);
        CSWAP(k[0], k[1]); CSWAP(k[2], k[3]); CSWAP(k[4], k[5]); CSWAP(k[6], k[7]);
        CSWAP(k[2], k[4]); CSWAP(k[3], k[5]);
        CSWAP(k[1], k[4]); CSWAP(k[3], k[6]);
        CSWAP(k[1], k[2]); CSWAP(k[3], k[4]); CSWAP(k[5], k[6]);
        for (int64_t j = 0; j < 8; j++) key[j] = k[j];
        return;
    }
    for (int64_t j = 1; j < n; j++) {
        const uint64_t kj = key[j];
        int64_t pos = j;
        while (pos > 0 && key[pos - 1] > kj) {
            key[pos] = key[pos - 1];
            pos--;
        }
        key[pos] = kj;
    }
}

/* Observations of one environment, (N, O) with O = 5 + 3 kt + 5 ka; see AGVEnv.observe.
 * dat (N, M) and daa (N, N) are the AGV-task and AGV-AGV distances; key holds max(N, M, 8). */
static void observe_env(int64_t N, int64_t M, int64_t kt, int64_t ka, float range,
                        const float *pos, const float *vel, const float *task, const uint8_t *claimed,
                        const int64_t *agent_task, const float *dat, const float *daa,
                        float *obs, uint64_t *key) {
    const int64_t O = 5 + 3 * kt + 5 * ka;
    for (int64_t i = 0; i < N; i++) {
        float *o = obs + i * O;
        const float px = pos[2 * i], py = pos[2 * i + 1];
        memset(o, 0, sizeof(float) * (size_t)O);
        o[0] = vel[2 * i];
        o[1] = vel[2 * i + 1];
        o[2] = px;
        o[3] = py;
        float *ot = o + 4;
        if (kt > 0) {
            for (int64_t j = 0; j < M; j++) {
                const float d = dat[i * M + j];
                key[j] = sort_key((claimed[j] || d > range) ? INF_F : d, j);
            }
            sort_keys(key, M);
            for (int64_t r = 0; r < kt && r < M && (key[r] >> 32) != INF_BITS; r++) {
                const int64_t j = (int64_t)(key[r] & 0xffffffffu);
                ot[3 * r] = task[2 * j] - px;
                ot[3 * r + 1] = task[2 * j + 1] - py;
                ot[3 * r + 2] = 1.0f;
            }
        }
        float *oa = ot + 3 * kt;
        if (ka > 0) {
            for (int64_t j = 0; j < N; j++) {
                const float d = daa[i * N + j];
                key[j] = sort_key((j == i || d > range) ? INF_F : d, j);
            }
            sort_keys(key, N);
            for (int64_t r = 0; r < ka && r < N && (key[r] >> 32) != INF_BITS; r++) {
                const int64_t j = (int64_t)(key[r] & 0xffffffffu);
                oa[5 * r] = pos[2 * j] - px;
                oa[5 * r + 1] = pos[2 * j + 1] - py;
                oa[5 * r + 2] = vel[2 * j];
                oa[5 * r + 3] = vel[2 * j + 1];
                oa[5 * r + 4] = 1.0f;
            }
        }
        o[O - 1] = agent_task[i] >= 0 ? 1.0f : 0.0f;
    }
}

/* AGV-task distances dat (N, M) and AGV-AGV distances daa (N, N) of one environment. */
static void distances(int64_t N, int64_t M, const float *pos, const float *task, float *dat,
                      float *daa) {
    for (int64_t i = 0; i < N; i++) {
        const float px = pos[2 * i], py = pos[2 * i + 1];
        for (int64_t j = 0; j < M; j++) {
            const float dx = task[2 * j] - px, dy = task[2 * j + 1] - py;
            dat[i * M + j] = sqrtf(dx * dx + dy * dy);
        }
        daa[i * N + i] = 0.0f;
        for (int64_t j = i + 1; j < N; j++) {
            const float dx = px - pos[2 * j], dy = py - pos[2 * j + 1];
            daa[i * N + j] = daa[j * N + i] = sqrtf(dx * dx + dy * dy);
        }
    }
}

/* Observations of B environments from their state (AGVEnv.observe). */
void agv_observe(int64_t B, int64_t N, int64_t M, int64_t kt, int64_t ka, float range,
                 const float *pos, const float *vel, const float *task, const uint8_t *claimed,
                 const int64_t *agent_task, float *obs) {
    const int64_t O = 5 + 3 * kt + 5 * ka;
    float *dat = malloc(sizeof(float) * (size_t)(N * M + N * N));
    float *daa = dat + N * M;
    uint64_t *key = malloc(sizeof(uint64_t) * (size_t)(N + M + 8));
    for (int64_t b = 0; b < B; b++) {
        const float *p = pos + b * N * 2, *t = task + b * M * 2;
        distances(N, M, p, t, dat, daa);
        observe_env(N, M, kt, ka, range, p, vel + b * N * 2, t, claimed + b * M,
                    agent_task + b * N, dat, daa, obs + b * N * O, key);
    }
    free(dat);
    free(key);
}

/* Everything the step does after the physics (AGVEnv.step): claims, step counter and done,
 * collisions, the team reward R_t, the AGV-task distances and the observations. Inputs are the
 * state after the physics and before the claims; every output is a fresh tensor. Collision
 * counts and the team reward are 0 in environments that were already done. */
void agv_post_step(int64_t B, int64_t N, int64_t M, int64_t kt, int64_t ka, float range,
                   float capture, float collide, int64_t max_steps,
                   const float *pos, const float *vel, const float *task, const uint8_t *claimed,
                   const int64_t *agent_task, const int64_t *steps, const uint8_t *done,
                   float *vel_out, int64_t *agent_task_out, uint8_t *claimed_out,
                   uint8_t *claimed_now, int64_t *steps_out, uint8_t *done_out, float *dist,
                   float *per_agent, float *pairs, float *team, float *obs) {
    const int64_t O = 5 + 3 * kt + 5 * ka;
    float *daa = malloc(sizeof(float) * (size_t)(N * N));
    uint64_t *key = malloc(sizeof(uint64_t) * (size_t)(N + M + 8));
    int64_t *best_agent = malloc(sizeof(int64_t) * (size_t)(M + 1));
    for (int64_t b = 0; b < B; b++) {
        const float *p = pos + b * N * 2, *v = vel + b * N * 2, *t = task + b * M * 2;
        const uint8_t *cl = claimed + b * M;
        const int64_t *at = agent_task + b * N;
        float *vo = vel_out + b * N * 2, *d = dist + b * N * M;
        int64_t *ato = agent_task_out + b * N;
        uint8_t *clo = claimed_out + b * M, *now = claimed_now + b * M;
        const int active = !done[b];
        distances(N, M, p, t, d, daa);
        memcpy(vo, v, sizeof(float) * (size_t)(N * 2));
        memcpy(ato, at, sizeof(int64_t) * (size_t)N);
        memcpy(clo, cl, (size_t)M);
        memset(now, 0, (size_t)M);
        /* Claims in one round: each task goes to its nearest eligible AGV, and an AGV that wins
         * several takes its nearest (first index on ties, as torch's min). */
        if (active) {
            for (int64_t j = 0; j < M; j++) {
                best_agent[j] = -1;
                if (cl[j]) continue;
                float best = INF_F;
                for (int64_t i = 0; i < N; i++) {
                    const float dij = d[i * M + j];
                    if (at[i] < 0 && dij <= capture && dij < best) {
                        best = dij;
                        best_agent[j] = i;
                    }
                }
            }
            for (int64_t i = 0; i < N; i++) {
                float best = INF_F;
                int64_t take = -1;
                for (int64_t j = 0; j < M; j++) {
                    if (best_agent[j] == i && d[i * M + j] < best) {
                        best = d[i * M + j];
                        take = j;
                    }
                }
                if (take >= 0) {
                    ato[i] = take;
                    vo[2 * i] *= 0.0f;
                    vo[2 * i + 1] *= 0.0f;
                    now[take] = 1;
                    clo[take] = 1;
                }
            }
        }
        steps_out[b] = steps[b] + (active ? 1 : 0);
        int all_claimed = 1;
        for (int64_t j = 0; j < M; j++) all_claimed &= clo[j] != 0;
        done_out[b] = done[b] || all_claimed || steps_out[b] >= max_steps;
        /* Collisions (discs overlapping) and the team reward R_t. */
        int64_t npairs = 0;
        for (int64_t i = 0; i < N; i++) {
            int64_t hits = 0;
            for (int64_t j = 0; j < N; j++) {
                const int hit = j != i && daa[i * N + j] < collide;
                hits += hit;
                npairs += hit && j > i;
            }
            per_agent[b * N + i] = active ? (float)hits : 0.0f;
        }
        pairs[b] = active ? (float)npairs : 0.0f;
        float nearest = 0.0f;
        for (int64_t j = 0; j < M; j++) {
            float m = INF_F;
            for (int64_t i = 0; i < N; i++) m = d[i * M + j] < m ? d[i * M + j] : m;
            nearest += m;
        }
        team[b] = active ? -nearest - (float)npairs : 0.0f;
        observe_env(N, M, kt, ka, range, p, vo, t, clo, ato, d, daa, obs + b * N * O, key);
    }
    free(daa);
    free(key);
    free(best_agent);
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
    uint8_t *cand = (uint8_t *)(cnt + 4 * B);  /* B T bytes in the last B T + 1 slots */
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
        int64_t mt = 0, na = 0, shared = 0;
        for (int pass = 0; pass < 2; pass++) {  /* tasks first in src, AGVs after */
            const int64_t lo = pass == 0 ? N : 0, hi = pass == 0 ? T : N;
            for (int64_t s = lo; s < hi; s++) {
                if (s < N) as[s] = -1;
                if (!ca[s]) continue;
                int shadowed = 0;
                for (int64_t e = 0; e < s && !shadowed; e++) shadowed = ca[e] && ce[e] == ce[s];
                shared |= shadowed;
                if (shadowed) continue;
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
        const int64_t *ce = cell + b * T, *sr = src + b * T, *as = aslot + b * N;
        const uint8_t *ca = cand + b * T;
        const int64_t mt = cnt[4 * b], na = cnt[4 * b + 1];
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
    }
    return status;
}

/* Clip n actions to [-1, 1] into out; returns how many were NaN or infinite (out is then
 * not to be used). */
int64_t agv_clip_actions(int64_t n, const float *a, float *out) {
    int64_t bad = 0;
    for (int64_t k = 0; k < n; k++) {
        const float x = a[k];
        bad += !isfinite(x);
        out[k] = x < -1.0f ? -1.0f : (x > 1.0f ? 1.0f : x);
    }
    return bad;
}

/* One round of spawning for entity k (Scenario.spawn): for each of the b environments still
 * to place, the first of its C candidates (b, C, 2) that passes ok (b, C; NULL = all) and
 * keeps squared distance >= gap2[j] to every earlier entity j < k of placed (B, E, 2). The
 * squared distance is summed as torch does, (dx * dx) + (dy * dy) in float32, so both paths
 * accept the same candidates. Writes placed[todo[i], k] and found[i]. */
void agv_spawn_pick(int64_t b, int64_t C, int64_t E, int64_t k, const float *cand,
                    const uint8_t *ok, const int64_t *todo, const float *gap2, float *placed,
                    uint8_t *found) {
    for (int64_t i = 0; i < b; i++) {
        float *row = placed + todo[i] * E * 2;
        found[i] = 0;
        for (int64_t c = 0; c < C && !found[i]; c++) {
            if (ok != NULL && !ok[i * C + c]) continue;
            const float cx = cand[(i * C + c) * 2], cy = cand[(i * C + c) * 2 + 1];
            int clear = 1;
            for (int64_t j = 0; j < k && clear; j++) {
                const float dx = cx - row[2 * j], dy = cy - row[2 * j + 1];
                const float sx = dx * dx, sy = dy * dy;
                clear = sx + sy >= gap2[j];
            }
            if (clear) {
                row[2 * k] = cx;
                row[2 * k + 1] = cy;
                found[i] = 1;
            }
        }
    }
}
