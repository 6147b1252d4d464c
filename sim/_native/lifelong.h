/* Lifelong operation (the torch references: sim/observations.py observe_lifelong,
 * sim/physics.py pair_distances and collisions, sim/tasks.py remaining_work): the
 * observations, the AGV-AGV distances and collisions of B floors in one pass per floor, and
 * the remaining work of the lifelong R_t. sim/lifelong_native.py calls them.
 *
 * Distances. The AGV-AGV distances are pair_distances': sqrt(dx * dx + dy * dy) in float32
 * with a correctly rounded sqrtf. The AGV-pickup, pickup-drop-off and AGV-drop-off lengths
 * are torch.linalg.vector_norm's and torch.cdist's, whose rounding depends on the CPU kernel
 * torch dispatches to: builds with fused multiply-add (AVX2, AVX-512) compute
 * sqrt(fma(dy, dy, dx * dx)), the others sqrt(dx * dx + dy * dy). The caller says which
 * (fused, found by sim/lifelong_native.py from torch itself), so the nearest pickups and the
 * sensing range see the very same float32 distances as the reference. */
#ifndef AGV_LIFELONG_H
#define AGV_LIFELONG_H

#include "common.h"
#include "observations.h" /* zero_slots() */

/* Order and AGV status codes (sim/orders.py). */
#define LL_OPEN 1
#define LL_ASSIGNED 2
#define LL_LOADED 3
#define LL_CARRYING 2
#define LL_BROKEN 3

/* |(dx, dy)| rounded as torch's vector_norm / cdist round it (see the top of the file). */
static inline __attribute__((always_inline)) float torch_norm(float dx, float dy, int fused) {
    return fused ? sqrtf(fmaf(dy, dy, dx * dx)) : sqrtf(dx * dx + dy * dy);
}

/* The k nearest entries of d[0..n) that are below INF, not above range and not entry skip:
 * their indices in bi[0..filled), nearest first (ties: lower index first, as torch's stable
 * sort), bd their distances; returns filled = min(k, how many there are). One pass with the
 * k-th distance so far as the bar; k >= 1. */
static inline __attribute__((always_inline)) int64_t ll_nearest(
        int64_t n, int64_t k, const float *d, float range, int64_t skip, float *bd,
        int64_t *bi) {
    int64_t filled = 0;
    float bar = INF_F;
    for (int64_t j = 0; j < n; j++) {
        const float x = d[j];
        if (!(x < bar) || x > range || j == skip) continue;
        int64_t at = filled < k ? filled++ : k - 1;
        while (at > 0 && bd[at - 1] > x) {
            bd[at] = bd[at - 1];
            bi[at] = bi[at - 1];
            at--;
        }
        bd[at] = x;
        bi[at] = j;
        if (filled == k) bar = bd[k - 1];
    }
    return filled;
}

/* The k nearest entries, as ll_nearest: in lanes for k <= VL (VL = 4 here). */
static inline __attribute__((always_inline)) int64_t ll_nearest_k(
        int64_t n, int64_t k, const float *d, float range, int64_t skip, float *bd,
        int64_t *bi) {
#if VL == 4
    if (k <= VL) return nearest_lanes(n, k, d, range, skip, bd, bi);
#endif
    return ll_nearest(n, k, d, range, skip, bd, bi);
}

/* Scratch of one lifelong call, sized for N AGVs, Q orders and k slots. */
typedef struct {
    float *ox, *oy, *dk, *bd;
    int64_t *oidx, *bi;
    void *heap;
} ll_scratch_t;

static int ll_scratch_init(ll_scratch_t *s, int64_t N, int64_t Q, int64_t k) {
    const int64_t L = (N > Q ? N : Q) + 1, K = k + 1;
    unsigned char *m = malloc(sizeof(float) * (size_t)(2 * Q + 2 + L + K)
                              + sizeof(int64_t) * (size_t)(Q + 1 + K));
    if (!m) return -1;
    s->heap = m;
    s->oidx = (int64_t *)(void *)m;
    s->bi = s->oidx + Q + 1;
    s->ox = (float *)(void *)(s->bi + K);
    s->oy = s->ox + Q + 1;
    s->dk = s->oy + Q + 1;
    s->bd = s->dk + L;
    return 0;
}

/* One floor of agv_lifelong_observe (see there). Returns 1 when a status code lies outside
 * 0..3, else 0. */
static inline __attribute__((always_inline)) int lifelong_env(
        int64_t N, int64_t Q, int64_t kp, int64_t ka, float range, int fused, float collide,
        const float *pos, const float *vel, const int8_t *status, const int64_t *service_left,
        const float *target, const uint8_t *has_target, const float *pickup,
        const int8_t *order_status, int active, float *obs, float *pair, float *per_agent,
        float *pairs, ll_scratch_t *s) {
    const int64_t O = 12 + 3 * kp + 5 * ka;
    int bad = 0;
    /* The AGV-AGV distances (pair_distances): each pair once, symmetric, 0 on the diagonal;
     * and the overlapping discs (collisions) from them. */
    for (int64_t i = 0; i < N; i++) {
        const float px = pos[2 * i], py = pos[2 * i + 1];
        pair[i * N + i] = 0.0f;
        for (int64_t j = i + 1; j < N; j++) {
            const float dx = px - pos[2 * j], dy = py - pos[2 * j + 1];
            const float d = sqrtf(dx * dx + dy * dy);
            pair[i * N + j] = pair[j * N + i] = d;
        }
    }
    if (per_agent) {
        int64_t twice = 0;
        for (int64_t i = 0; i < N; i++) {
            int64_t hits = 0;
            for (int64_t j = 0; j < N; j++) hits += (j != i) & (pair[i * N + j] < collide);
            per_agent[i] = active ? (float)hits : 0.0f;
            twice += hits;
        }
        *pairs = active ? (float)(twice / 2) : 0.0f;
    }
    /* The open orders, in slot order (so that ties still go to the lower slot). */
    int64_t nopen = 0;
    if (kp > 0)
        for (int64_t q = 0; q < Q; q++) {
            if (order_status[q] != LL_OPEN) continue;
            s->oidx[nopen] = q;
            s->ox[nopen] = pickup[2 * q];
            s->oy[nopen] = pickup[2 * q + 1];
            nopen++;
        }
    for (int64_t i = 0; i < N; i++) {
        float *o = obs + i * O;
        const float px = pos[2 * i], py = pos[2 * i + 1];
        const int st = status[i];
        bad |= st < 0 || st > 3;
        o[0] = vel[2 * i];
        o[1] = vel[2 * i + 1];
        o[2] = px;
        o[3] = py;
        o[4] = st == 0 ? 1.0f : 0.0f;
        o[5] = st == 1 ? 1.0f : 0.0f;
        o[6] = st == 2 ? 1.0f : 0.0f;
        o[7] = st == 3 ? 1.0f : 0.0f;
        o[8] = service_left[i] > 0 ? 1.0f : 0.0f;
        const int has = has_target[i] != 0;
        o[9] = has ? target[2 * i] - px : 0.0f;
        o[10] = has ? target[2 * i + 1] - py : 0.0f;
        o[11] = has ? 1.0f : 0.0f;
        float *op = o + 12, *oa = op + 3 * kp;
        if (kp > 0) {
            /* All distances first (a loop the compiler vectorizes), then the selection. */
            float *dk = s->dk;
            const float *ox = s->ox, *oy = s->oy;
            for (int64_t c = 0; c < nopen; c++) dk[c] = torch_norm(ox[c] - px, oy[c] - py, fused);
            const int64_t filled = ll_nearest_k(nopen, kp, dk, range, -1, s->bd, s->bi);
            for (int64_t r = 0; r < filled; r++) {
                const int64_t c = s->bi[r];
                op[3 * r] = ox[c] - px;
                op[3 * r + 1] = oy[c] - py;
                op[3 * r + 2] = 1.0f;
            }
            zero_slots(op, filled, kp, 3);
        }
        if (ka > 0) {
            const int64_t filled = ll_nearest_k(N, ka, pair + i * N, range, i, s->bd, s->bi);
            for (int64_t r = 0; r < filled; r++) {
                const int64_t j = s->bi[r];
                oa[5 * r] = pos[2 * j] - px;
                oa[5 * r + 1] = pos[2 * j + 1] - py;
                oa[5 * r + 2] = vel[2 * j];
                oa[5 * r + 3] = vel[2 * j + 1];
                oa[5 * r + 4] = 1.0f;
            }
            zero_slots(oa, filled, ka, 5);
        }
    }
    return bad;
}

/* The floors' loop, with fused a compile-time constant; a copy for CPUs with FMA on x86-64
 * (fmaf is then one instruction and the distances vectorize), the portable one calls fmaf. */
#define LL_FLOORS(fused)                                                                     \
    for (int64_t b = 0; b < B; b++)                                                          \
        bad |= lifelong_env(N, Q, kp, ka, range, fused, collide, pos + b * N * 2,            \
                            vel + b * N * 2, status + b * N, service_left + b * N,           \
                            target + b * N * 2, has_target + b * N, pickup + b * Q * 2,      \
                            order_status + b * Q, active ? active[b] != 0 : 0,               \
                            obs + b * N * O, pair + b * N * N,                               \
                            per_agent ? per_agent + b * N : NULL,                            \
                            per_agent ? pairs + b : NULL, s)
#define LL_FLOORS_PARAMS                                                                     \
    int64_t B, int64_t N, int64_t Q, int64_t kp, int64_t ka, float range, float collide,    \
    const float *pos, const float *vel, const int8_t *status, const int64_t *service_left,  \
    const float *target, const uint8_t *has_target, const float *pickup,                    \
    const int8_t *order_status, const uint8_t *active, float *obs, float *pair,             \
    float *per_agent, float *pairs, ll_scratch_t *s

static int ll_floors_plain(LL_FLOORS_PARAMS) {
    const int64_t O = 12 + 3 * kp + 5 * ka;
    int bad = 0;
    LL_FLOORS(0);
    return bad;
}

static int ll_floors_fused(LL_FLOORS_PARAMS) {
    const int64_t O = 12 + 3 * kp + 5 * ka;
    int bad = 0;
    LL_FLOORS(1);
    return bad;
}

#if defined(__x86_64__) && defined(__GNUC__)
#define LL_HAVE_FMA_COPY 1
__attribute__((target("avx2,fma"))) static int ll_floors_fma(LL_FLOORS_PARAMS) {
    const int64_t O = 12 + 3 * kp + 5 * ka;
    int bad = 0;
    LL_FLOORS(1);
    return bad;
}
#endif

/* Lifelong observations of B floors (observe_lifelong), obs (B, N, O) with
 * O = 12 + 3 kp + 5 ka, and the AGV-AGV distances pair (B, N, N) (pair_distances); with
 * per_agent (B, N) and pairs (B) not NULL also the overlapping discs (collisions: distance
 * below collide, 0 where active (B) is 0). The pickups shown are those of OPEN orders
 * (order_status (B, Q)) within range, the k nearest by torch_norm(fused); the AGVs the k
 * nearest others within range by pair. Ties go to the lower index, as torch's stable sort.
 * Every entry of the outputs is written. Returns -1 when out of memory, 1 when an AGV status
 * lies outside 0..3 (the outputs are then incomplete), else 0. */
int agv_lifelong_observe(int64_t B, int64_t N, int64_t Q, int64_t kp, int64_t ka, float range,
                         int fused, float collide, const float *pos, const float *vel,
                         const int8_t *status, const int64_t *service_left, const float *target,
                         const uint8_t *has_target, const float *pickup,
                         const int8_t *order_status, const uint8_t *active, float *obs,
                         float *pair, float *per_agent, float *pairs) {
    ll_scratch_t s;
    if (ll_scratch_init(&s, N, Q, kp > ka ? kp : ka)) return -1;
    if (per_agent == NULL || pairs == NULL || active == NULL) per_agent = pairs = NULL;
    int bad;
#define LL_ARGS B, N, Q, kp, ka, range, collide, pos, vel, status, service_left, target, \
                has_target, pickup, order_status, active, obs, pair, per_agent, pairs, &s
    if (!fused)
        bad = ll_floors_plain(LL_ARGS);
#ifdef LL_HAVE_FMA_COPY
    else if (__builtin_cpu_supports("fma") && __builtin_cpu_supports("avx2"))
        bad = ll_floors_fma(LL_ARGS);
#endif
    else
        bad = ll_floors_fused(LL_ARGS);
#undef LL_ARGS
    free(s.heap);
    return bad;
}

static inline __attribute__((always_inline)) int remaining_work_floors(
        int64_t B, int64_t N, int64_t Q, int fused_cdist, int fused_norm, const float *pos,
        const int8_t *order_status, const float *pickup, const float *dropoff,
        const int64_t *order_agent, const int8_t *agent_status, const uint8_t *active,
        float *out) {
    int bad = 0;
    for (int64_t b = 0; b < B; b++) {
        const float *p = pos + b * N * 2, *pk = pickup + b * Q * 2, *dr = dropoff + b * Q * 2;
        const int8_t *os = order_status + b * Q, *as = agent_status + b * N;
        const int64_t *oa = order_agent + b * Q;
        int any = 0;
        for (int64_t i = 0; i < N; i++) any |= as[i] != LL_CARRYING && as[i] != LL_BROKEN;
        double sum = 0.0;
        for (int64_t q = 0; q < Q; q++) {
            const int st = os[q];
            const int64_t a = oa[q] < 0 ? 0 : oa[q];
            bad |= a >= N;
            if (st == LL_OPEN || st == LL_ASSIGNED) {
                const float x = pk[2 * q], y = pk[2 * q + 1];
                float near = N > 0 ? INF_F : 0.0f;
                for (int64_t i = 0; i < N; i++) {
                    const int avail = !any || (as[i] != LL_CARRYING && as[i] != LL_BROKEN);
                    const float d = torch_norm(x - p[2 * i], y - p[2 * i + 1], fused_cdist);
                    near = avail && d < near ? d : near;
                }
                const float trip = torch_norm(dr[2 * q] - x, dr[2 * q + 1] - y, fused_norm);
                sum += (double)(near + trip);
            } else if (st == LL_LOADED && a < N) {
                sum += (double)torch_norm(p[2 * a] - dr[2 * q], p[2 * a + 1] - dr[2 * q + 1],
                                          fused_norm);
            }
        }
        out[b] = active[b] ? (float)sum : 0.0f;
    }
    return bad;
}

#define LL_WORK_PARAMS                                                                       \
    int64_t B, int64_t N, int64_t Q, int fused_cdist, int fused_norm, const float *pos,     \
    const int8_t *order_status, const float *pickup, const float *dropoff,                  \
    const int64_t *order_agent, const int8_t *agent_status, const uint8_t *active,          \
    float *out
#define LL_WORK_ARGS B, N, Q, fused_cdist, fused_norm, pos, order_status, pickup, dropoff, \
                     order_agent, agent_status, active, out

static int ll_work_portable(LL_WORK_PARAMS) {
    return remaining_work_floors(LL_WORK_ARGS);
}

#ifdef LL_HAVE_FMA_COPY
__attribute__((target("avx2,fma"))) static int ll_work_fma(LL_WORK_PARAMS) {
    return remaining_work_floors(LL_WORK_ARGS);
}
#endif

/* The remaining work of B floors (remaining_work), out (B): per order, an OPEN or ASSIGNED
 * one its pickup's distance to the nearest available AGV (status neither CARRYING nor
 * BROKEN; the nearest AGV at all when none is) plus its pickup to drop-off length, a LOADED
 * one its AGV's (order_agent, negative read as 0) distance to the drop-off, others 0; summed
 * per floor in double and rounded once, 0 where active is 0. fused_cdist and fused_norm say
 * how torch.cdist and torch.linalg.vector_norm round (see the top of the file). Returns 1
 * when an order's AGV index is N or more (torch's gather refuses it), else 0. */
int agv_lifelong_remaining_work(int64_t B, int64_t N, int64_t Q, int fused_cdist,
                                int fused_norm, const float *pos, const int8_t *order_status,
                                const float *pickup, const float *dropoff,
                                const int64_t *order_agent, const int8_t *agent_status,
                                const uint8_t *active, float *out) {
#ifdef LL_HAVE_FMA_COPY
    if ((fused_cdist || fused_norm) && __builtin_cpu_supports("fma")
            && __builtin_cpu_supports("avx2"))
        return ll_work_fma(LL_WORK_ARGS);
#endif
    return ll_work_portable(LL_WORK_ARGS);
}

#endif /* AGV_LIFELONG_H */
