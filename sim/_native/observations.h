/* Observations (the torch reference: sim/observations.py observe): the K nearest
 * visible tasks and AGVs of each AGV, in scalar code and in lanes.
 *
 * Each entry point's feature order is sim.observations.ObsLayout's. */
#ifndef AGV_OBSERVATIONS_H
#define AGV_OBSERVATIONS_H

#include "common.h"

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

/* The lanes of a shifted up by one, lane 0 from b's lane 0: {b0, a0, a1, a2} (VL = 4). */
#if defined(__clang__)
#define LANE_SHIFT_UP(a, b) __builtin_shufflevector(a, b, 4, 0, 1, 2)
#else
#define LANE_SHIFT_UP(a, b) __builtin_shuffle(a, b, (vi){4, 0, 1, 2})
#endif

/* The k <= VL nearest entries of d[0..n) that are below INF, not above range and not entry
 * skip, nearest first (ties: the lower index first): their indices in bi, their distances in
 * bd; returns how many (at most k). Without a branch per entry: the VL nearest so far are kept
 * sorted in a vector of distances and one of indices, each entry is compared with all of them
 * at once, and the lanes from its place on shift up by one. An entry equal to a kept one goes
 * after it, and one not below INF (infinite, NaN, beyond range, skip) never enters, so the
 * result is exactly the insertion sort's (nearest below, ll_nearest in lifelong.h), whose
 * branches mispredict about once per entry; this is 2-3x faster at 20-40 entries. */
static inline __attribute__((always_inline)) int64_t nearest_lanes(
        int64_t n, int64_t k, const float *d, float range, int64_t skip, float *bd,
        int64_t *bi) {
    vf best = vf_fill(INF_F);
    const vi zero = {0};
    vi idx = zero;
    for (int64_t j = 0; j < n; j++) {
        float x = d[j];
        x = (x > range || j == skip) ? INF_F : x;
        const vf xv = vf_fill(x);
        const vi jv = zero + (int32_t)j;
        const vi later = best > xv;  /* a suffix of the lanes, as best is sorted */
        const vi moved = LANE_SHIFT_UP(later, zero);  /* lanes that take their left neighbour */
        best = vf_pick(later, vf_pick(moved, LANE_SHIFT_UP(best, xv), xv), best);
        idx = (later & ((moved & LANE_SHIFT_UP(idx, jv)) | (~moved & jv))) | (~later & idx);
    }
    int64_t filled = 0;
    while (filled < k && best[filled] < INF_F) {
        bd[filled] = best[filled];
        bi[filled] = idx[filled];
        filled++;
    }
    return filled;
}

/* order[r] = the index of the r-th nearest finite entry of dk[0..n) (ties: lower index
 * first), for r < min(k, number of finite entries), which is returned; by insertion into the
 * k places kept (for lists longer than SMALL). */
static int64_t nearest(int64_t n, int64_t k, const float *dk, int64_t *order) {
#if VL == 4
    if (k <= VL) {
        float bd[VL];
        return nearest_lanes(n, k, dk, INF_F, -1, bd, order);
    }
#endif
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

#endif /* AGV_OBSERVATIONS_H */
