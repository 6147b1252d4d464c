/* The exported step kernels (sim/env.py calls them): the actions' check and masks
 * (agv_prepare), the fused step after the physics (agv_post_step) and the observations
 * from a state (agv_observe). Compiled as part of kernels.c. */
#include "common.h"
#include "observations.h"
#include "physics.h"
#include "tasks.h"

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
