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
/* Small fixed sizes: stack scratch up to this many AGVs or tasks, heap beyond. */
#define SMALL 8

/* rank[j] = the place of entry j of dk[0..n), n <= SMALL, in increasing order (ties: lower
 * index first, as torch's stable sort; infinite entries last); returns how many are finite.
 * By comparing each pair once: branch-free, no dependency chains. */
static inline __attribute__((always_inline)) int64_t ranks(int64_t n, const float *dk,
                                                           int64_t *rank) {
    int64_t found = 0;
    for (int64_t j = 0; j < n; j++) rank[j] = 0;
    for (int64_t j = 0; j < n; j++) {
        for (int64_t l = j + 1; l < n; l++) {  /* a tie goes to the lower index, j */
            const int64_t after = dk[l] < dk[j];
            rank[j] += after;
            rank[l] += 1 - after;
        }
        found += dk[j] < INF_F;
    }
    return found;
}

/* order[r] = the index of the r-th nearest finite entry of dk[0..n) (ties: lower index
 * first), for r < min(k, number of finite entries), which is returned; by insertion into the
 * k places kept (for lists longer than SMALL). */
static int64_t nearest(int64_t n, int64_t k, const float *dk, int64_t *order) {
    int64_t filled = 0;
    for (int64_t j = 0; j < n; j++) {
        const float d = dk[j];
        if (!(d < INF_F) || (filled == k && d >= dk[order[k - 1]])) continue;
        int64_t pos = filled < k ? filled++ : k - 1;
        while (pos > 0 && dk[order[pos - 1]] > d) {
            order[pos] = order[pos - 1];
            pos--;
        }
        order[pos] = j;
    }
    return filled;
}

/* x where mask is all ones, +0 where it is 0: a select without a branch. */
static inline __attribute__((always_inline)) float keep(float x, uint32_t mask) {
    uint32_t u;
    memcpy(&u, &x, sizeof u);
    u &= mask;
    memcpy(&x, &u, sizeof u);
    return x;
}

/* A task's entry at dst: its offset and the mask bit, or zeros where mask is 0 (mask: all
 * ones or 0). */
#define PUT_TASK(dst, j, mask)                                \
    do {                                                      \
        const uint32_t keep_ = (mask);                        \
        float *dst_ = (dst);                                  \
        dst_[0] = keep(task[2 * (j)] - px, keep_);            \
        dst_[1] = keep(task[2 * (j) + 1] - py, keep_);        \
        dst_[2] = keep(1.0f, keep_);                          \
    } while (0)
/* An AGV's entry: the other AGV's offset, its velocity and the mask bit, or zeros. */
#define PUT_AGENT(dst, j, mask)                               \
    do {                                                      \
        const uint32_t keep_ = (mask);                        \
        float *dst_ = (dst);                                  \
        dst_[0] = keep(pos[2 * (j)] - px, keep_);             \
        dst_[1] = keep(pos[2 * (j) + 1] - py, keep_);         \
        dst_[2] = keep(vel[2 * (j)], keep_);                  \
        dst_[3] = keep(vel[2 * (j) + 1], keep_);              \
        dst_[4] = keep(1.0f, keep_);                          \
    } while (0)
/* Zeros slots from..k-1 of width w at out (the padding of a K-nearest list). */
static inline __attribute__((always_inline)) void zero_slots(float *out, int64_t from, int64_t k,
                                                             int64_t w) {
    for (int64_t r = from; r < k; r++)
        for (int64_t c = 0; c < w; c++) out[w * r + c] = 0.0f;
}

/* Fills the k slots of width w at out with the k nearest finite entries of dk[0..n), in
 * increasing order, then zeros. Short lists write each entry straight to the slot of its rank,
 * long ones go through the k nearest. */
#define PUT_NEAREST(n, k, w, out, put)                                        \
    do {                                                                      \
        int64_t filled;                                                       \
        if ((n) <= SMALL) {                                                   \
            int64_t rk[SMALL];                                                \
            const int64_t found = ranks(n, dk, rk);                           \
            for (int64_t j = 0; j < (n); j++)                                 \
                if (dk[j] < INF_F && rk[j] < (k)) put((out) + (w) * rk[j], j, ~0u); \
            filled = found < (k) ? found : (k);                               \
        } else {                                                              \
            filled = nearest(n, k, dk, order);                                \
            for (int64_t r = 0; r < filled; r++) put((out) + (w) * r, order[r], ~0u); \
        }                                                                     \
        zero_slots(out, filled, k, w);                                        \
    } while (0)

/* Scenes of VL + 1 to SMALL AGVs and at most SMALL tasks are done with all AGVs at once: AGV i
 * sits in lane i % VL of vector i / VL (GCC and Clang vector extensions; plain SSE2 on
 * x86-64). Up to VL AGVs the scalar code is faster: one vector would be mostly empty. */
#define VL 4
#define CH (SMALL / VL)
typedef float vf __attribute__((vector_size(4 * VL)));
typedef int32_t vi __attribute__((vector_size(4 * VL)));

static inline __attribute__((always_inline)) vf vf_sqrt(vf x) {
    vf r;
    for (int l = 0; l < VL; l++) r[l] = sqrtf(x[l]);  /* one instruction where there is one */
    return r;
}

/* mask ? y : x, lane by lane (mask lanes are 0 or -1). */
static inline __attribute__((always_inline)) vf vf_pick(vi mask, vf y, vf x) {
    return (vf)((mask & (vi)y) | (~mask & (vi)x));
}

/* Whether a scene of N AGVs and M tasks is done in lanes. */
#define USES_LANES(N, M) (VL < (N) && (N) <= SMALL && (M) <= SMALL)

/* {0, 1, ..., VL - 1}: each lane's index. */
static inline __attribute__((always_inline)) vi vi_lanes(void) {
    vi r;
    for (int l = 0; l < VL; l++) r[l] = l;
    return r;
}

static inline __attribute__((always_inline)) vf vf_fill(float x) {
    vf r;
    for (int l = 0; l < VL; l++) r[l] = x;
    return r;
}

/* The distances of a small scene in lanes: dt[j] from the AGVs to task j, da[j] to AGV j
 * (0 to itself). Each is sqrt(dx * dx + dy * dy), correctly rounded, as everywhere else. */
typedef struct {
    vf px[CH], py[CH], dt[SMALL][CH], da[SMALL][CH];
} lanes_t;

static inline __attribute__((always_inline)) void lanes_init(
        int64_t N, int64_t M, const float *pos, const float *task, lanes_t *g) {
    const int64_t nc = (N + VL - 1) / VL;
    for (int64_t c = 0; c < nc; c++)
        for (int l = 0; l < VL; l++) {
            const int64_t i = VL * c + l;
            g->px[c][l] = i < N ? pos[2 * i] : 0.0f;
            g->py[c][l] = i < N ? pos[2 * i + 1] : 0.0f;
        }
    for (int64_t j = 0; j < M; j++)
        for (int64_t c = 0; c < nc; c++) {
            const vf dx = task[2 * j] - g->px[c], dy = task[2 * j + 1] - g->py[c];
            g->dt[j][c] = vf_sqrt(dx * dx + dy * dy);
        }
    for (int64_t j = 0; j < N; j++)
        for (int64_t c = 0; c < nc; c++) {
            const vf dx = g->px[c] - pos[2 * j], dy = g->py[c] - pos[2 * j + 1];
            g->da[j][c] = vf_sqrt(dx * dx + dy * dy);
        }
}

/* ranks() in every lane: adds to rank[j] (zeroed by the caller) how many entries of d[0..n)
 * come before entry j. after = -1 in the lanes where entry m comes before entry j. */
static inline __attribute__((always_inline)) void lane_ranks(int64_t n, int64_t nc,
                                                             vf (*d)[CH], vi (*rank)[CH]) {
    for (int64_t j = 0; j < n; j++)
        for (int64_t m = j + 1; m < n; m++)
            for (int64_t c = 0; c < nc; c++) {
                const vi after = d[m][c] < d[j][c];
                rank[j][c] -= after;
                rank[m][c] += 1 + after;
            }
}

/* observe_env for a small scene from its distances in lanes: the hidden entries and the
 * ranks of all AGVs at once (as ranks() does), then each AGV's entries written to the slots
 * of their ranks, hidden ones as zeros and ranks past k to a junk slot (see PUT_NEAREST). */
static inline __attribute__((always_inline)) void observe_lanes(
        int64_t N, int64_t M, int64_t kt, int64_t ka, float range, const lanes_t *g,
        const float *pos, const float *vel, const float *task, const uint8_t *claimed,
        const int64_t *agent_task, float *obs) {
    const int64_t O = 5 + 3 * kt + 5 * ka, nc = (N + VL - 1) / VL;
    const vf inf = vf_fill(INF_F);
    vf dt[SMALL][CH], da[SMALL][CH];
    vi rt[SMALL][CH], ra[SMALL][CH];
    const vi lane = vi_lanes(), zero = {0};
    for (int64_t j = 0; j < M; j++) {
        const vi hidden = claimed[j] ? zero - 1 : zero;
        for (int64_t c = 0; c < nc; c++) {
            dt[j][c] = vf_pick(hidden | (g->dt[j][c] > range), inf, g->dt[j][c]);
            rt[j][c] = zero;
        }
    }
    for (int64_t j = 0; j < N; j++)
        for (int64_t c = 0; c < nc; c++) {
            const vi self = lane + (int32_t)(VL * c) == (int32_t)j;
            da[j][c] = vf_pick(self | (g->da[j][c] > range), inf, g->da[j][c]);
            ra[j][c] = zero;
        }
    lane_ranks(M, nc, dt, rt);
    lane_ranks(N, nc, da, ra);
    float junk[8];
    for (int64_t i = 0; i < N; i++) {
        const int64_t c = i / VL, l = i % VL;
        const float px = pos[2 * i], py = pos[2 * i + 1];
        float *o = obs + i * O, *ot = o + 4, *oa = ot + 3 * kt;
        o[0] = vel[2 * i];
        o[1] = vel[2 * i + 1];
        o[2] = px;
        o[3] = py;
        for (int64_t j = 0; j < M; j++) {
            const int32_t r = rt[j][c][l];
            PUT_TASK(r < kt ? ot + 3 * r : junk, j, -(uint32_t)(dt[j][c][l] < INF_F));
        }
        zero_slots(ot, M, kt, 3);
        for (int64_t j = 0; j < N; j++) {
            const int32_t r = ra[j][c][l];
            PUT_AGENT(r < ka ? oa + 5 * r : junk, j, -(uint32_t)(da[j][c][l] < INF_F));
        }
        zero_slots(oa, N, ka, 5);
        o[O - 1] = agent_task[i] >= 0 ? 1.0f : 0.0f;
    }
}

/* Observations of one environment, (N, O) with O = 5 + 3 kt + 5 ka; see AGVEnv.observe.
 * dat (N, M) and daa (N, N) are the AGV-task and AGV-AGV distances; dk and order hold
 * max(N, M) entries (used for lists longer than SMALL). Every entry of obs is written once. */
static inline __attribute__((always_inline)) void observe_env(
        int64_t N, int64_t M, int64_t kt, int64_t ka, float range, const float *pos,
        const float *vel, const float *task, const uint8_t *claimed, const int64_t *agent_task,
        const float *dat, const float *daa, float *obs, float *dk_long, int64_t *order) {
    const int64_t O = 5 + 3 * kt + 5 * ka;
    float dk_short[SMALL];
    for (int64_t i = 0; i < N; i++) {
        float *o = obs + i * O;
        const float px = pos[2 * i], py = pos[2 * i + 1];
        o[0] = vel[2 * i];
        o[1] = vel[2 * i + 1];
        o[2] = px;
        o[3] = py;
        if (kt > 0) {
            float *dk = M <= SMALL ? dk_short : dk_long;
            for (int64_t j = 0; j < M; j++) {
                const float d = dat[i * M + j];
                dk[j] = (claimed[j] || d > range) ? INF_F : d;
            }
            PUT_NEAREST(M, kt, 3, o + 4, PUT_TASK);
        }
        if (ka > 0) {
            float *dk = N <= SMALL ? dk_short : dk_long;
            for (int64_t j = 0; j < N; j++) {
                const float d = daa[i * N + j];
                dk[j] = (j == i || d > range) ? INF_F : d;
            }
            PUT_NEAREST(N, ka, 5, o + 4 + 3 * kt, PUT_AGENT);
        }
        o[O - 1] = agent_task[i] >= 0 ? 1.0f : 0.0f;
    }
}
#undef PUT_TASK
#undef PUT_AGENT
#undef PUT_NEAREST

/* Scratch of one kernel call: on the stack for small scenes, else on the heap. */
typedef struct {
    float daa_s[SMALL * SMALL], dk_s[SMALL], colmin_s[SMALL];
    int64_t order_s[SMALL], best_s[SMALL], hits_s[SMALL];
    float *daa, *dk, *colmin;
    int64_t *order, *best, *hits;
    void *heap;
} scratch_t;

static int scratch_init(scratch_t *s, int64_t N, int64_t M) {
    const int64_t L = N > M ? N : M;
    s->heap = NULL;
    if (L <= SMALL) {
        s->daa = s->daa_s; s->dk = s->dk_s; s->colmin = s->colmin_s;
        s->order = s->order_s; s->best = s->best_s; s->hits = s->hits_s;
        return 0;
    }
    float *f = malloc(sizeof(float) * (size_t)(N * N + 2 * L) + sizeof(int64_t) * (size_t)(3 * L));
    if (!f) return -1;
    s->heap = f;
    s->daa = f; s->dk = f + N * N; s->colmin = s->dk + L;
    int64_t *g = (int64_t *)(void *)(s->colmin + L);
    s->order = g; s->best = g + L; s->hits = g + 2 * L;
    return 0;
}

/* The first pass of a step over the pairs of a scene: the AGV-task distances d (N, M) and
 * the AGV-AGV distances daa (N, N), each task's nearest AGV colmin (M) (for R_t), the
 * overlapping discs of each AGV hits (N), and whether an idle AGV reached an open task
 * (close). Returns the number of overlapping pairs. */
static inline __attribute__((always_inline)) int64_t pairs_scalar(
        int64_t N, int64_t M, float capture, float collide, const float *p, const float *t,
        const uint8_t *cl, const int64_t *at, float *d, float *daa, float *colmin,
        int64_t *hits, int *close) {
    int64_t npairs = 0;
    int near = 0;
    for (int64_t j = 0; j < M; j++) colmin[j] = INF_F;
    for (int64_t i = 0; i < N; i++) hits[i] = 0;
    for (int64_t i = 0; i < N; i++) {
        const float px = p[2 * i], py = p[2 * i + 1];
        const int idle = at[i] < 0;
        for (int64_t j = 0; j < M; j++) {
            const float dx = t[2 * j] - px, dy = t[2 * j + 1] - py;
            const float dij = sqrtf(dx * dx + dy * dy);
            d[i * M + j] = dij;
            colmin[j] = dij < colmin[j] ? dij : colmin[j];
            near |= idle & !cl[j] & (dij <= capture);
        }
        daa[i * N + i] = 0.0f;
        for (int64_t j = i + 1; j < N; j++) {
            const float dx = px - p[2 * j], dy = py - p[2 * j + 1];
            const float dij = sqrtf(dx * dx + dy * dy);
            daa[i * N + j] = daa[j * N + i] = dij;
            const int hit = dij < collide;
            hits[i] += hit;
            hits[j] += hit;
            npairs += hit;
        }
    }
    *close = near;
    return npairs;
}

/* Calls body(N, M, kt, ka) with compile-time sizes for the paper's scenes (3v3, 6v6), so the
 * small loops unroll, and with the run-time sizes otherwise. */
#define SPECIALIZE(body)                                                                     \
    do {                                                                                     \
        if (N == 3 && M == 3 && kt == 3 && ka == 2) body(3, 3, 3, 2);                        \
        else if (N == 6 && M == 6 && kt == 6 && ka == 5) body(6, 6, 6, 5);                   \
        else body(N, M, kt, ka);                                                             \
    } while (0)

static inline __attribute__((always_inline)) void observe_envs(
        int64_t B, const int64_t N, const int64_t M, const int64_t kt, const int64_t ka,
        float range, const float *pos, const float *vel, const float *task,
        const uint8_t *claimed, const int64_t *agent_task, float *obs, float *dat,
        scratch_t *s) {
    const int64_t O = 5 + 3 * kt + 5 * ka;
    for (int64_t b = 0; b < B; b++) {
        const float *p = pos + b * N * 2, *t = task + b * M * 2;
        if (USES_LANES(N, M)) {
            lanes_t g;
            lanes_init(N, M, p, t, &g);
            observe_lanes(N, M, kt, ka, range, &g, p, vel + b * N * 2, t, claimed + b * M,
                          agent_task + b * N, obs + b * N * O);
        } else {
            int close;  /* the step's first pass; only the distances are used here */
            pairs_scalar(N, M, 0.0f, 0.0f, p, t, claimed + b * M, agent_task + b * N, dat,
                         s->daa, s->colmin, s->hits, &close);
            observe_env(N, M, kt, ka, range, p, vel + b * N * 2, t, claimed + b * M,
                        agent_task + b * N, dat, s->daa, obs + b * N * O, s->dk, s->order);
        }
    }
}

/* Observations of B environments from their state (AGVEnv.observe). Returns -1 when out of
 * memory, else 0. */
int agv_observe(int64_t B, int64_t N, int64_t M, int64_t kt, int64_t ka, float range,
                const float *pos, const float *vel, const float *task, const uint8_t *claimed,
                const int64_t *agent_task, float *obs) {
    scratch_t s;
    float *dat = malloc(sizeof(float) * (size_t)(N * M + 1));
    if (!dat || scratch_init(&s, N, M)) {
        free(dat);
        return -1;
    }
#define OBSERVE(n, m, k1, k2) \
    observe_envs(B, n, m, k1, k2, range, pos, vel, task, claimed, agent_task, obs, dat, &s)
    SPECIALIZE(OBSERVE);
#undef OBSERVE
    free(dat);
    free(s.heap);
    return 0;
}

/* pairs_scalar for a small scene whose AGV-AGV distances g holds: the same values, with the
 * tasks in lanes for d, colmin and close. */
static inline __attribute__((always_inline)) int64_t pairs_lanes(
        int64_t N, int64_t M, float capture, float collide, const lanes_t *g, const float *p,
        const float *t, const uint8_t *cl, const int64_t *at, float *d, float *daa,
        float *colmin, int64_t *hits, int *close) {
    const int64_t nc = (N + VL - 1) / VL, mc = (M + VL - 1) / VL;
    vi hit[CH], open[CH];
    const vi lane = vi_lanes(), zero = {0};
    /* Row j of daa is da[j] (the distances are symmetric); hits counted in the AGVs' lanes. */
    for (int64_t c = 0; c < nc; c++) hit[c] = zero;
    for (int64_t j = 0; j < N; j++) {
        memcpy(daa + j * N, g->da[j], sizeof(float) * (size_t)N);
        for (int64_t c = 0; c < nc; c++)
            hit[c] -= (g->da[j][c] < collide) & (lane + (int32_t)(VL * c) != (int32_t)j);
    }
    int64_t twice = 0;
    for (int64_t i = 0; i < N; i++) {
        hits[i] = hit[i / VL][i % VL];
        twice += hits[i];
    }
    /* The tasks in lanes: row i of d, and the running minimum over the AGVs. */
    vf tx[CH], ty[CH], cm[CH];
    vi near = zero;
    for (int64_t c = 0; c < mc; c++) {
        for (int l = 0; l < VL; l++) {
            const int64_t j = VL * c + l;
            tx[c][l] = j < M ? t[2 * j] : 0.0f;
            ty[c][l] = j < M ? t[2 * j + 1] : 0.0f;
            open[c][l] = j < M && !cl[j] ? -1 : 0;
        }
        cm[c] = vf_fill(INF_F);
    }
    for (int64_t i = 0; i < N; i++) {
        const float px = p[2 * i], py = p[2 * i + 1];
        const vi idle = at[i] < 0 ? zero - 1 : zero;
        for (int64_t c = 0; c < mc; c++) {
            const vf dx = tx[c] - px, dy = ty[c] - py;
            const vf dij = vf_sqrt(dx * dx + dy * dy);
            const int64_t width = M - VL * c < VL ? M - VL * c : VL;
            memcpy(d + i * M + VL * c, &dij, sizeof(float) * (size_t)width);
            cm[c] = vf_pick(dij < cm[c], dij, cm[c]);
            near |= (dij <= capture) & idle & open[c];
        }
    }
    memcpy(colmin, cm, sizeof(float) * (size_t)M);
    int any = 0;
    for (int l = 0; l < VL; l++) any |= near[l] != 0;
    *close = any;
    return twice / 2;
}

/* The rest of one environment's step after the first pass (see agv_post_step): claims, step
 * counter and done, collisions and R_t; returns the change flags. */
static inline __attribute__((always_inline)) int finish_env(
        const int64_t N, const int64_t M, float capture, int64_t max_steps, float *v,
        const uint8_t *cl, const int64_t *at, int64_t steps, uint8_t done, int64_t *ato,
        uint8_t *clo, uint8_t *now, int64_t *steps_out, uint8_t *done_out, const float *d,
        float *per_agent, float *pairs, float *team, float *team_distance,
        float *team_collision, const float *colmin, const int64_t *hits, int64_t npairs,
        int close, int64_t *best_agent) {
    const int active = !done;
    int flags = 0;
    memcpy(ato, at, sizeof(int64_t) * (size_t)N);
    memcpy(clo, cl, (size_t)M);
    memset(now, 0, (size_t)M);
    /* Claims in one round: each task goes to its nearest eligible AGV, and an AGV that wins
     * several takes its nearest (first index on ties, as torch's min). */
    if (active && close) {
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
                v[2 * i] *= 0.0f;
                v[2 * i + 1] *= 0.0f;
                now[take] = 1;
                clo[take] = 1;
                flags |= 1;
            }
        }
    }
    *steps_out = steps + (active ? 1 : 0);
    int all_claimed = 1;
    for (int64_t j = 0; j < M; j++) all_claimed &= clo[j] != 0;
    *done_out = done || all_claimed || *steps_out >= max_steps;
    flags |= (*done_out != done) << 1;
    /* Collisions (discs overlapping) and the team reward R_t. */
    for (int64_t i = 0; i < N; i++) per_agent[i] = active ? (float)hits[i] : 0.0f;
    const float fpairs = active ? (float)npairs : 0.0f;
    float nearest_sum = 0.0f;
    for (int64_t j = 0; j < M; j++) nearest_sum += colmin[j];
    const float r_t = active ? -nearest_sum - (float)npairs : 0.0f;
    *pairs = fpairs;
    *team = r_t;
    /* R_t split per AGV as the MiniDist reward reports it (the same float32 sums as torch). */
    for (int64_t i = 0; i < N; i++) {
        team_distance[i] = r_t + fpairs;
        team_collision[i] = -fpairs;
    }
    return flags;
}

/* One environment of agv_post_step; returns its change flags (see there). */
static inline __attribute__((always_inline)) int post_step_env(
        const int64_t N, const int64_t M, const int64_t kt, const int64_t ka, float range,
        float capture, float collide, int64_t max_steps, const float *p, float *v,
        const float *t, const uint8_t *cl, const int64_t *at, int64_t steps, uint8_t done,
        int64_t *ato, uint8_t *clo, uint8_t *now, int64_t *steps_out, uint8_t *done_out,
        float *d, float *daa, float *per_agent, float *pairs, float *team,
        float *team_distance, float *team_collision, float *obs, scratch_t *s) {
    int close, flags;
    int64_t npairs;
#define FINISH()                                                                             \
    finish_env(N, M, capture, max_steps, v, cl, at, steps, done, ato, clo, now, steps_out,   \
               done_out, d, per_agent, pairs, team, team_distance, team_collision, s->colmin, \
               s->hits, npairs, close, s->best)
    if (USES_LANES(N, M)) {
        lanes_t g;
        lanes_init(N, M, p, t, &g);
        npairs = pairs_lanes(N, M, capture, collide, &g, p, t, cl, at, d, daa, s->colmin,
                             s->hits, &close);
        flags = FINISH();
        observe_lanes(N, M, kt, ka, range, &g, p, v, t, clo, ato, obs);
    } else {
        npairs = pairs_scalar(N, M, capture, collide, p, t, cl, at, d, daa, s->colmin, s->hits,
                              &close);
        flags = FINISH();
        observe_env(N, M, kt, ka, range, p, v, t, clo, ato, d, daa, obs, s->dk, s->order);
    }
#undef FINISH
    return flags;
}

/* Everything the step does after the physics (AGVEnv.step): claims, step counter and done,
 * collisions, the team reward R_t, the AGV-task distances and the observations, from the
 * state after the physics and before the claims, the AGV-AGV distances pair_dist (B, N, N)
 * (which the next physics step reuses), and R_t split per AGV into the MiniDist
 * reward's terms (team_distance = R_t + pairs, team_collision = -pairs, both (B, N)).
 * Collision counts and the team reward are 0 in environments that were already done.
 *
 * vel (B, N, 2) is the physics step's fresh output and is updated in place (AGVs that claim
 * stop). agent_task_out, claimed_out and done_out always receive the new values; the return
 * value says whether they differ from the inputs: bit 0 when a task was claimed (agent_task,
 * claimed), bit 1 when an environment finished (done); -1 when out of memory. */
int agv_post_step(int64_t B, int64_t N, int64_t M, int64_t kt, int64_t ka, float range,
                  float capture, float collide, int64_t max_steps,
                  const float *pos, float *vel, const float *task, const uint8_t *claimed,
                  const int64_t *agent_task, const int64_t *steps, const uint8_t *done,
                  int64_t *agent_task_out, uint8_t *claimed_out, uint8_t *claimed_now,
                  int64_t *steps_out, uint8_t *done_out, float *dist, float *pair_dist,
                  float *per_agent, float *pairs, float *team, float *team_distance,
                  float *team_collision, float *obs) {
    scratch_t s;
    int flags = 0;
    if (scratch_init(&s, N, M)) return -1;
#define POST_STEP(n, m, k1, k2)                                                               \
    for (int64_t b = 0; b < B; b++)                                                           \
        flags |= post_step_env(n, m, k1, k2, range, capture, collide, max_steps,              \
                               pos + b * n * 2, vel + b * n * 2, task + b * m * 2,            \
                               claimed + b * m, agent_task + b * n, steps[b], done[b],        \
                               agent_task_out + b * n, claimed_out + b * m,                   \
                               claimed_now + b * m, steps_out + b, done_out + b,              \
                               dist + b * n * m, pair_dist + b * n * n, per_agent + b * n,   \
                               pairs + b, team + b,                                           \
                               team_distance + b * n, team_collision + b * n,                 \
                               obs + b * n * (5 + 3 * k1 + 5 * k2), &s)
    SPECIALIZE(POST_STEP);
#undef POST_STEP
    free(s.heap);
    return flags;
}

/* Checks the actions a (B, N, 2) and writes the masks the step needs: active (B) = not
 * done, movable (B, N) = active and idle. Returns the number of NaN or infinite actions, or -1
 * when all are finite but some lie outside [-1, 1] (the caller clips them), else 0. */
int64_t agv_prepare(int64_t B, int64_t N, const float *a, const int64_t *agent_task,
                    const uint8_t *done, uint8_t *movable, uint8_t *active) {
    /* On the bit patterns, so that the loop vectorizes: all exponent bits set = NaN or
     * infinite; |x| > 1 = magnitude bits above those of 1.0f. */
    int64_t bad = 0;
    uint32_t outside = 0;
    for (int64_t k = 0; k < B * N * 2; k++) {
        uint32_t bits;
        memcpy(&bits, a + k, sizeof bits);
        const uint32_t mag = bits & 0x7fffffffu;
        bad += (mag >= 0x7f800000u);
        outside |= (mag > 0x3f800000u);
    }
    for (int64_t k = 0; k < B * N; k++) movable[k] = (uint8_t)((uint64_t)agent_task[k] >> 63);
    for (int64_t b = 0; b < B; b++) {
        active[b] = !done[b];
        if (done[b]) memset(movable + b * N, 0, (size_t)N);
    }
    return bad ? bad : -(int64_t)(outside != 0);
}

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
