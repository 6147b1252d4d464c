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
#include "streams.h"

#define PK_PARAMS                                                                           \
    int64_t B, int64_t N, int64_t Q, float cap, int fused, int norm_fused,                  \
    const float *agent_pos, const uint8_t *ready, const int64_t *agent_order,               \
    const float *pickup, const float *dropoff, const int8_t *status, const int64_t *key,    \
    uint8_t *takes, int64_t *slot, uint8_t *at_drop
#define PK_ARGS B, N, Q, cap, fused, norm_fused, agent_pos, ready, agent_order, pickup, \
                dropoff, status, key, takes, slot, at_drop

static inline __attribute__((always_inline)) int pickups_floors(PK_PARAMS) {
    unsigned char *scratch = arena_reserve((size_t)Q * (3 * sizeof(float) + 2 * sizeof(int64_t))
                                           + (size_t)N * (sizeof(float) + sizeof(int64_t)));
    if (!scratch && (Q || N)) return -1;
    float *best_d = (float *)scratch;
    int64_t *best_a = (int64_t *)(best_d + Q);
    float *won_d = (float *)(best_a + Q);
    int64_t *won_key = (int64_t *)(won_d + N);
    int64_t *open_q = won_key + N;  /* the OPEN orders of the floor, in slot order */
    float *open_x = (float *)(open_q + Q), *open_y = open_x + Q;
    for (int64_t b = 0; b < B; b++) {
        const float *ap = agent_pos + 2 * b * N;
        const float *pp = pickup + 2 * b * Q;
        const float *dp = dropoff + 2 * b * Q;
        const int8_t *st = status + b * Q;
        const int64_t *ky = key + b * Q;
        uint8_t *tk = takes + b * N;
        int64_t *sl = slot + b * N;
        int64_t nopen = 0;
        for (int64_t q = 0; q < Q; q++) {
            best_d[q] = INF_F;
            best_a[q] = -1;
            if (st[q] != LL_OPEN) continue;
            open_q[nopen] = q;
            open_x[nopen] = pp[2 * q];
            open_y[nopen++] = pp[2 * q + 1];
        }
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
            const float ax = ap[2 * a], ay = ap[2 * a + 1];
            if (own >= 0) {  /* only its own order, if it is still assigned */
                if (st[own] != LL_ASSIGNED) continue;
                const float d = torch_norm(ax - pp[2 * own], ay - pp[2 * own + 1], fused);
                if (d <= cap && d < best_d[own]) { best_d[own] = d; best_a[own] = a; }
                continue;
            }
            /* Any open order: the list of open ones, with no branch on the status. */
            for (int64_t c = 0; c < nopen; c++) {
                const float d = torch_norm(ax - open_x[c], ay - open_y[c], fused);
                const int64_t q = open_q[c];
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

static int pickups_portable(PK_PARAMS) { return pickups_floors(PK_ARGS); }

#ifdef LL_HAVE_FMA_COPY
/* With FMA, torch_norm's fmaf is one instruction instead of a call into libm. */
__attribute__((target("avx2,fma"))) static int pickups_fma(PK_PARAMS) {
    return pickups_floors(PK_ARGS);
}
#endif

/* Returns 0, or -1 when the scratch space cannot be allocated. */
int agv_lifelong_pickups(int64_t B, int64_t N, int64_t Q, float cap, int fused,
                         int norm_fused, const float *agent_pos, const uint8_t *ready,
                         const int64_t *agent_order, const float *pickup, const float *dropoff,
                         const int8_t *status, const int64_t *key, uint8_t *takes,
                         int64_t *slot, uint8_t *at_drop) {
#ifdef LL_HAVE_FMA_COPY
    if ((fused || norm_fused) && __builtin_cpu_supports("fma") && __builtin_cpu_supports("avx2"))
        return pickups_fma(PK_ARGS);
#endif
    return pickups_portable(PK_ARGS);
}
#undef PK_PARAMS
#undef PK_ARGS

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

/* The backlog's arrivals of one step (sim/lifelong.py LifelongEnv._arrivals with a Backlog):
 * counts[b] = max(open - (OPEN + ASSIGNED orders of floor b), 0) where rows[b], else 0.
 * Returns the sum of the counts. */
int64_t agv_backlog_counts(int64_t B, int64_t Q, const int8_t *status, const uint8_t *rows,
                           int64_t open, int64_t *counts) {
    int64_t total = 0;
    for (int64_t b = 0; b < B; b++) {
        int64_t n = 0;
        for (int64_t q = 0; q < Q; q++) {
            const int8_t st = status[b * Q + q];
            n += st == LL_OPEN || st == LL_ASSIGNED;
        }
        const int64_t c = rows[b] && open > n ? open - n : 0;
        counts[b] = c;
        total += c;
    }
    return total;
}

/* uniform(key, stream, id, part) of sim/streams.py (agv_uniform with three counters). */
static inline double order_draw(uint64_t key, int64_t stream, int64_t id, int64_t part) {
    return stream_unit(stream_fold(stream_fold(stream_fold(key, stream), id), part));
}

/* Generated orders released in one step (sim/orders.py insert_orders with generated_points):
 * floor b's counts[b] new orders take its lowest FREE slots, in slot order, with ids
 * next_id[b], next_id[b] + 1, ...; each one's pickup is points[i] and drop-off stations[j]
 * with i = floor(u0 P) and j = floor(u1 S) (clamped to P - 1 and S - 1), u_k =
 * uniform(key[b], stream, id, k); status OPEN, release step[b], priority 0, deadline
 * step[b] + deadline_after when deadline_after > 0 (else -1), agent, picked and finished -1.
 * The order table (the ten (B, Q) fields, pickup and dropoff (B, Q, 2)) is read from the
 * first ten pointers and written, whole, to the next ten (a new table: the inputs are not
 * changed); arrived (B, Q) marks the new rows and next_out (B) = next_id + counts. Returns 0,
 * or 1 when some floor has fewer FREE slots than its count (nothing is written then). */
int agv_insert_generated(int64_t B, int64_t Q, const int64_t *counts, const int64_t *next_id,
                         const int64_t *step, const int64_t *key, int64_t stream, int64_t P,
                         const float *points, int64_t S, const float *stations,
                         int64_t deadline_after, const int64_t *id, const int8_t *status,
                         const float *pickup, const float *dropoff, const int64_t *release,
                         const int64_t *priority, const int64_t *deadline,
                         const int64_t *agent, const int64_t *picked, const int64_t *finished,
                         int64_t *id_o, int8_t *status_o, float *pickup_o, float *dropoff_o,
                         int64_t *release_o, int64_t *priority_o, int64_t *deadline_o,
                         int64_t *agent_o, int64_t *picked_o, int64_t *finished_o,
                         uint8_t *arrived, int64_t *next_out) {
    for (int64_t b = 0; b < B; b++) {
        int64_t free_slots = 0;
        for (int64_t q = 0; q < Q; q++) free_slots += status[b * Q + q] == 0;
        if (counts[b] > free_slots) return 1;
    }
    const size_t n = (size_t)(B * Q);
    memcpy(id_o, id, n * sizeof(int64_t));
    memcpy(status_o, status, n);
    memcpy(pickup_o, pickup, 2 * n * sizeof(float));
    memcpy(dropoff_o, dropoff, 2 * n * sizeof(float));
    memcpy(release_o, release, n * sizeof(int64_t));
    memcpy(priority_o, priority, n * sizeof(int64_t));
    memcpy(deadline_o, deadline, n * sizeof(int64_t));
    memcpy(agent_o, agent, n * sizeof(int64_t));
    memcpy(picked_o, picked, n * sizeof(int64_t));
    memcpy(finished_o, finished, n * sizeof(int64_t));
    memset(arrived, 0, n);
    for (int64_t b = 0; b < B; b++) {
        int64_t r = 0;
        for (int64_t q = 0; q < Q && r < counts[b]; q++) {
            const int64_t k = b * Q + q;
            if (status[k] != 0) continue;
            const int64_t oid = next_id[b] + r++;
            int64_t i = (int64_t)(order_draw((uint64_t)key[b], stream, oid, 0) * (double)P);
            int64_t j = (int64_t)(order_draw((uint64_t)key[b], stream, oid, 1) * (double)S);
            i = i < P - 1 ? i : P - 1;
            j = j < S - 1 ? j : S - 1;
            id_o[k] = oid;
            status_o[k] = LL_OPEN;
            pickup_o[2 * k] = points[2 * i];
            pickup_o[2 * k + 1] = points[2 * i + 1];
            dropoff_o[2 * k] = stations[2 * j];
            dropoff_o[2 * k + 1] = stations[2 * j + 1];
            release_o[k] = step[b];
            priority_o[k] = 0;
            deadline_o[k] = deadline_after > 0 ? step[b] + deadline_after : -1;
            agent_o[k] = picked_o[k] = finished_o[k] = -1;
            arrived[k] = 1;
        }
        next_out[b] = next_id[b] + counts[b];
    }
    return 0;
}

#endif
