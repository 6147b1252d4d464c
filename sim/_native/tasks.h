/* The task rules after the pair pass (the torch references: sim/tasks.py claim and
 * team_reward): claims, step counter and done, the collision counts and R_t. */
#ifndef AGV_TASKS_H
#define AGV_TASKS_H

#include "common.h"

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

#endif /* AGV_TASKS_H */
