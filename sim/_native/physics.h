/* Pair geometry of a step (the torch references: sim/physics.py pair_distances and
 * collisions, sim/env.py's AGV-task distances): the first pass over the pairs of a scene. */
#ifndef AGV_PHYSICS_H
#define AGV_PHYSICS_H

#include "common.h"

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

#endif /* AGV_PHYSICS_H */
