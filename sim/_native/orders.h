/* Lifelong pickups (the torch reference: the eligibility in sim/lifelong.py LifelongEnv.step
 * and sim/orders.py match): which AGV picks which order up in this step, for B floors.
 *
 * An AGV that is ready (running, working, not in service, not finishing a drop-off) may pick
 * up its own assigned order, or, when it has none, any open order, within the capture radius.
 * Each order goes to its nearest eligible AGV (ties: the lower index); an AGV that wins
 * several takes its nearest, equally near ones by the larger key (priority, then age), then
 * the lower slot. Distances are torch.cdist's (torch_norm in lifelong.h).
 *
 * In the same pass, the drop-offs (sim.orders.dropoffs): a ready AGV whose order is loaded
 * and whose drop-off is within the capture radius (torch.linalg.vector_norm's rounding). An
 * AGV that picks up in this step has no loaded order before it, so it is never among them. */
#ifndef AGV_ORDERS_H
#define AGV_ORDERS_H

#include "common.h"
#include "lifelong.h"

/* Returns 0, or -1 when the scratch space cannot be allocated. */
int agv_lifelong_pickups(int64_t B, int64_t N, int64_t Q, float cap, int fused,
                         int norm_fused, const float *agent_pos, const uint8_t *ready,
                         const int64_t *agent_order, const float *pickup, const float *dropoff,
                         const int8_t *status, const int64_t *key, uint8_t *takes,
                         int64_t *slot, uint8_t *at_drop) {
    unsigned char *scratch = arena_reserve((size_t)Q * (sizeof(float) + sizeof(int64_t))
                                           + (size_t)N * (sizeof(float) + sizeof(int64_t)));
    if (!scratch && (Q || N)) return -1;
    float *best_d = (float *)scratch;
    int64_t *best_a = (int64_t *)(best_d + Q);
    float *won_d = (float *)(best_a + Q);
    int64_t *won_key = (int64_t *)(won_d + N);
    for (int64_t b = 0; b < B; b++) {
        const float *ap = agent_pos + 2 * b * N;
        const float *pp = pickup + 2 * b * Q;
        const float *dp = dropoff + 2 * b * Q;
        const int8_t *st = status + b * Q;
        const int64_t *ky = key + b * Q;
        uint8_t *tk = takes + b * N;
        int64_t *sl = slot + b * N;
        for (int64_t q = 0; q < Q; q++) { best_d[q] = INF_F; best_a[q] = -1; }
        for (int64_t a = 0; a < N; a++) {
            tk[a] = 0;
            sl[a] = 0;
            at_drop[b * N + a] = 0;
            if (!ready[b * N + a]) continue;
            const int64_t own = agent_order[b * N + a];
            if (own >= 0 && st[own] == LL_LOADED) {
                const float d = torch_norm(ap[2 * a] - dp[2 * own],
                                           ap[2 * a + 1] - dp[2 * own + 1], norm_fused);
                at_drop[b * N + a] = d <= cap;
                continue;
            }
            const int64_t q0 = own >= 0 ? own : 0, q1 = own >= 0 ? own + 1 : Q;
            const int8_t want = own >= 0 ? LL_ASSIGNED : LL_OPEN;
            for (int64_t q = q0; q < q1; q++) {
                if (st[q] != want) continue;
                const float d = torch_norm(ap[2 * a] - pp[2 * q], ap[2 * a + 1] - pp[2 * q + 1],
                                           fused);
                if (d <= cap && d < best_d[q]) { best_d[q] = d; best_a[q] = a; }
            }
        }
        for (int64_t q = 0; q < Q; q++) {
            const int64_t a = best_a[q];
            if (a < 0) continue;
            const float d = best_d[q];
            if (!tk[a] || d < won_d[a] || (d == won_d[a] && ky[q] > won_key[a])) {
                tk[a] = 1; sl[a] = q; won_d[a] = d; won_key[a] = ky[q];
            }
        }
    }
    return 0;
}

/* Each AGV's status and target (sim/orders.py agent_status, sim/lifelong.py targets): broken
 * while repair_left > 0, else loaded / to pickup by its order's status, else idle; the target
 * is a loaded AGV's drop-off or an assigned AGV's pickup, times has (0 otherwise), with the
 * order slot clamped to 0 as the torch gathers do. */
void agv_lifelong_status(int64_t B, int64_t N, int64_t Q, const int64_t *order,
                         const int64_t *repair_left, const int8_t *ostatus, const float *pickup,
                         const float *dropoff, int8_t *status, float *target, uint8_t *has) {
    for (int64_t b = 0; b < B; b++) {
        for (int64_t a = 0; a < N; a++) {
            const int64_t k = b * N + a, o = order[k];
            const int64_t q = o > 0 ? o : 0;
            const int8_t st = Q ? ostatus[b * Q + q] : 0;
            int8_t code = 0;
            if (repair_left[k] > 0) code = LL_BROKEN;
            else if (o >= 0 && st == LL_LOADED) code = LL_CARRYING;
            else if (o >= 0 && st == LL_ASSIGNED) code = 1;
            status[k] = code;
            const int h = code == 1 || code == LL_CARRYING;
            has[k] = (uint8_t)h;
            const float *src = (code == LL_CARRYING ? dropoff : pickup) + 2 * (b * Q + q);
            const float scale = (float)h;
            target[2 * k] = Q ? src[0] * scale : 0.0f;
            target[2 * k + 1] = Q ? src[1] * scale : 0.0f;
        }
    }
}

#endif
